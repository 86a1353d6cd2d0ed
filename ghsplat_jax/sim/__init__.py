"""Robot sensor simulation: the robot, its trajectories and its camera and LiDAR sensors, and
the time-stamped sensor stream as ROS 2 messages (no ROS installation needed). Sinks and
transports of that stream (bag, DDS, Foxglove, viewer) are in transport/, AprilTag
localization in localize/.

    frames.py         rigid transforms, REP-103 / OpenCV optical axes, a small tf tree
    robot.py          Jackal-sized robot, sensor mounts, map -> base_link -> camera_link ->
                      camera_optical_frame and base_link -> lidar_link
    trajectory.py     waypoint files, differential drive, aisle-following paths
    camera_sensor.py  pinhole cameras + CameraInfo; one compilation per image size
    beams.py          LiDAR beam patterns (VLP-16, HDL-32E, OS1-64, custom tables)
    lidar.py          four 90-degree z-depth faces (one vmap in one jit) -> beam pattern
    messages.py       ROS 2 messages via rosbags' typesys (the single source of truth: the
                      stream is made of them, every transport carries them)
    simulate.py       the time-stamped sensor stream along a trajectory
    scene_io.py       a simulation scene from a layout TOML or a composed PLY with its tags
    motion_args.py    the robot and trajectory options of `ghsplat simulate` and `ghsplat localize`
                      (commands/simulate.py, commands/localize.py)

Heavy dependencies (jax rendering, rosbags, cv2) are imported by the modules that need them.
"""
