"""Experiments: the layer that combines the ones below (SfM, the synthetic generator,
training, evaluation, rendering) into measured tables. `ghsplat run experiments/NAME.toml`
(commands/run.py) calls it; only commands and the CLI sit above it.

    runner.py        experiment files: scenes x config variants, finished runs skipped, the
                     local executor, rows collected into the reports
    ray_executor.py  the same runs as one Ray task each
    report.py        results table (markdown + CSV + JSON) and the Table-1 report
    charts.py        speed / accuracy / count scatter charts and Pareto fronts
    compactness.py   the compactness report (count fractions of the default run)
    segments.py      greenhouse row segments for files with [prepare]: photos, SfM scored
                     against the exact cameras
    stability.py     the stability study (kind = "stability"): where methods fail, how the
                     tool detects it and what it tells the user
    sfm_rows.py      SfM on procedural rows against ground truth (shared with the SfM
                     disambiguation benchmark)
"""
