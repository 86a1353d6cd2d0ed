"""Structure from motion for greenhouse rows: pycolmap (CPU, offline) and greenhouse alignment.

    from ghsplat_jax.sfm.pipeline import SfmOptions, run_sfm
    report = run_sfm("photos/", "scene/", SfmOptions(matching="exhaustive"))

Modules (import the one you need; pycolmap and cv2 load only there):

- pipeline.py: extraction -> matching -> mapping -> alignment -> undistortion; writes
  OUT/images, OUT/sparse/0 (PINHOLE, COLMAP binary), OUT/sfm_report.json.
- align.py: the greenhouse similarity (z up, row along +x, open end at +x) as pure
  numpy functions; the robust ground-plane fit uses optimistix.
- frames.py: sharp, well-spread keyframes from a video or a frame folder.
- evaluate.py: Umeyama alignment and pose errors against a reference model.
- report.py: reconstruction statistics, plain advice when images fail to register, and the
  outcome of a run as an exit status and message (verdict).
- `ghsplat sfm` is ghsplat_jax/commands/sfm.py.
"""
