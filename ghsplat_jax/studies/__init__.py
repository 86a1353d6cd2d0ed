"""Studies: experiments that need more than training (data made by synth and SfM, stability
cases); `ghsplat run` dispatches to them. The top layer beside commands."""
