"""Robot sensor simulation and the ROS 2 interface (no ROS installation needed).

    frames.py         rigid transforms, REP-103 / OpenCV optical axes, a small tf tree
    robot.py          Jackal-sized robot, sensor mounts, map -> base_link -> camera_link ->
                      camera_optical_frame and base_link -> lidar_link
    trajectory.py     waypoint files, differential drive, aisle-following paths
    camera_sensor.py  pinhole cameras + CameraInfo; one compilation per image size
    beams.py          LiDAR beam patterns (VLP-16, HDL-32E, OS1-64, custom tables)
    lidar.py          four 90-degree z-depth faces (one vmap in one jit) -> beam pattern
    messages.py       ROS 2 messages via rosbags' typesys (the single source of truth)
    recorder.py       rosbag2 bags with MCAP storage
    dds_types.py      the same messages as Cyclone DDS IDL types (rmw_cyclonedds names)
    dds_node.py       live node: /camera_pose in; render, /camera_info, /lidar, /tf out;
                      /register_camera (sensor_msgs/srv/SetCameraInfo)
    simulate.py       the time-stamped sensor stream along a trajectory
    localize.py       AprilTag detection and localization evaluation
    viewer.py         viser web viewer
    motion_args.py    the robot and trajectory options of `ghsplat simulate` and `ghsplat localize`
                      (commands/simulate.py, commands/localize.py)

Heavy dependencies (jax rendering, rosbags, cyclonedds, cv2, viser) are imported by the
modules that need them.
"""
