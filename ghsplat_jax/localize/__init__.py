"""AprilTag localization on rendered frames and its report (`ghsplat localize`).

    apriltag.py  detection (cv2.aruco, 36h11), camera and robot pose from the tags, and the
                 evaluation along a trajectory against ground truth (frames_along, evaluate)
    report.py    markdown summary, chart and the report folder (write_report)

It builds on the simulator (sim/: robot, camera sensor, trajectories), never the reverse.
"""
