"""Sinks and transports for the simulated sensor stream (sim/simulate.py yields it as ROS 2
messages, sim/messages.py), with no ROS installation needed.

    recorder.py       rosbag2 bags with MCAP storage
    dds_types.py      the messages as Cyclone DDS IDL types (rmw_cyclonedds names)
    dds_node.py       live node: /camera_pose in; render, /camera_info, /lidar, /tf out;
                      /register_camera (sensor_msgs/srv/SetCameraInfo); a stream sink
    foxglove_sink.py  the stream served to Foxglove over its WebSocket protocol
    viewer.py         viser web viewer of scene, robot, image and LiDAR

It builds on the simulator (sim/), never the reverse. Heavy dependencies (rosbags,
cyclonedds, foxglove-sdk, viser) are imported by the modules that need them.
"""
