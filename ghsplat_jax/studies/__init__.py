"""Studies that combine the layers below (SfM, the synthetic generator, training, rendering) into
one measured table: `ghsplat run experiments/NAME.toml` dispatches here. The top layer, beside
commands.

    segments.py    greenhouse row segments for files with [prepare]: photos, SfM scored
                   against the exact cameras
    stability.py   where methods fail, how the tool detects it and what it tells the user
    sfm_rows.py    SfM on procedural rows against ground truth (shared with
                   benchmarks/sfm_disambiguation.py)
"""
