"""Scene tools: editing, transforms, composition, markers, mesh extraction (PLY I/O is
data/ply.py, below training, which writes and reads PLYs too).

    edit       crops (box, sphere, convex hull), opacity, NaN/Inf, floaters -> (Surfels, kept_mask)
    stats      per-file statistics as a JSON-ready dict
    transform  rescale, rigid transform and mirror with SH rotation (core.sh_rotation)
    merge      SH-degree policy (pad / truncate), no silent 3DGS + 2DGS mixing
    surfaces   floor / wall surfels from rectangles, boxes or trimesh meshes
    markers    AprilTag 36h11 markers as surfels, ground-truth Tag poses (tags.py)
    layout     greenhouse layout TOML; compose builds the scene from it
    tsdf       depth fusion into a TSDF and marching-cubes meshes
    views      shape-stable renders and orbit cameras for the tools above
    export     the `ghsplat export` pipeline: merge, clean, transform, write (and a mesh)

Modules import their heavy dependencies (scipy, cv2, trimesh, OpenImageIO, skimage) on use.
"""
