"""`ghsplat simulate`: drive a Jackal-sized robot through a scene and record or publish
its camera, LiDAR and tf as ROS 2 messages (no ROS installation needed).

    ghsplat simulate greenhouse.toml --trajectory aisles --record run.mcap
    ghsplat simulate scene.ply --trajectory path.csv --live --domain-id 7
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
import tomllib

from ghsplat_jax.sim import motion_args

HELP = "Simulate the robot's camera, LiDAR and tf in a scene; record a ROS 2 bag (MCAP) or publish live over DDS."


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", metavar="LAYOUT_OR_PLY", help="layout .toml (composed in memory) or scene .ply")
    p.add_argument("--tags", metavar="tags.json", help="marker poses (default: <stem>.tags.json beside a PLY)")
    motion_args.add_arguments(p)
    p.add_argument("--duration", type=float, help="simulated seconds to run (default: the whole trajectory)")
    p.add_argument("--max-events", type=int, help="stop after this many sensor frames (quick runs)")
    p.add_argument("--camera-rate", type=float, default=10.0, help="Hz (0: no camera)")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--fov", type=float, default=70.0, help="horizontal field of view, degrees")
    p.add_argument("--depth", action="store_true", help="also publish /render_depth (32FC1 z-depth)")
    p.add_argument("--normals", action="store_true", help="also publish /render_normals (32FC3, world frame)")
    p.add_argument("--lidar", default="vlp16", help="vlp16 | hdl32e | os1-64 | beam table .json/.csv | none")
    p.add_argument("--lidar-rate", type=float, help="Hz (default: the pattern's spin rate)")
    p.add_argument("--lidar-face-width", type=int, help="pixels per 90-degree face (default: about columns/pi)")
    p.add_argument("--lidar-depth", choices=("expected", "median"), default="median",
                   help="median depth avoids ghost points between leaves and what is behind")
    p.add_argument("--range-noise", type=float, help="Gaussian range noise std (m), overrides the pattern")
    p.add_argument("--lidar-batching", choices=("vmap", "map"), default="map",
                   help="render the four faces one after another in one jit (lax.map, default: the "
                        "rasterizer skips unused work, less memory) or as one vmap")
    p.add_argument("--lidar-sampling", choices=("beams", "faces"), default="beams",
                   help="render only the beams' rays (default: exact, about 3x faster) or whole face "
                        "images resampled onto the beams")
    p.add_argument("--organised", action="store_true", help="organised cloud (rings x columns, NaN = no return)")
    p.add_argument("--record", metavar="run.mcap",
                   help="write a rosbag2 bag with MCAP storage (run.mcap -> run/run.mcap)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing bag")
    p.add_argument("--live", action="store_true", help="publish over DDS as a ROS 2 node and serve /register_camera")
    p.add_argument("--domain-id", type=int, default=0, help="ROS_DOMAIN_ID for --live")
    p.add_argument("--any-interface", action="store_true",
                   help="--live: use Cyclone's default network setup instead of loopback only")
    p.add_argument("--real-time", type=float, default=1.0, metavar="FACTOR",
                   help="--live, --foxglove: pace simulated time at FACTOR x wall clock (0: as fast as possible)")
    p.add_argument("--linger", type=float, default=0.0,
                   help="keep serving (--live, --foxglove) or showing (--viewer) this many seconds "
                        "after the trajectory")
    p.add_argument("--foxglove", action="store_true",
                   help="serve the topics to Foxglove over its WebSocket protocol (pip install -e \".[foxglove]\")")
    p.add_argument("--port", type=int, default=8765, help="--foxglove: WebSocket port")
    p.add_argument("--host", default="127.0.0.1",
                   help="--foxglove: address to bind (default loopback only; 0.0.0.0 serves other machines)")
    p.add_argument("--viewer", action="store_true", help="show scene, robot, image and LiDAR in a viser web viewer")
    p.add_argument("--viewer-port", type=int, default=8080)
    p.add_argument("--quiet", action="store_true")


def main(args) -> int:
    from tqdm.auto import tqdm

    from ghsplat_jax.sim import beams, scene_io, simulate
    from ghsplat_jax.sim.camera_sensor import CameraModel, CameraRenderer
    from ghsplat_jax.sim.lidar import Lidar

    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO,
                        format="ghsplat simulate: %(levelname)s %(message)s")
    say = (lambda *a: None) if args.quiet else (lambda msg: print(f"ghsplat simulate: {msg}", file=sys.stderr))
    # Everything that can fail on input is checked before any file or DDS entity is created.
    try:
        robot = motion_args.load_robot(args.robot)
        scene = scene_io.load_scene(args.scene, args.tags)
        traj = motion_args.load_trajectory(args, scene, robot)
        pattern = None
        if args.lidar.lower() != "none":
            pattern = beams.get_pattern(args.lidar)
            if args.range_noise is not None:
                pattern = pattern.replace(noise_std=args.range_noise)
        camera = CameraModel.from_fov(robot.optical_frame, args.width, args.height, args.fov)
        if args.record:
            from ghsplat_jax.transport.recorder import bag_dir

            if bag_dir(args.record).exists() and not args.overwrite:
                raise FileExistsError(f"{bag_dir(args.record)}: already exists (use --overwrite)")
        if not (args.record or args.live or args.viewer or args.foxglove):
            raise ValueError("nothing to do: give --record, --live, --foxglove and/or --viewer")
        if args.foxglove:
            try:
                import foxglove  # noqa: F401
            except ImportError:
                raise ValueError('--foxglove needs foxglove-sdk: pip install -e ".[foxglove]"') from None
    except (ValueError, FileNotFoundError, FileExistsError, tomllib.TOMLDecodeError, OSError) as exc:
        print(f"ghsplat simulate: error: {exc}", file=sys.stderr)
        return 2
    say(f"scene {scene.path} ({scene.num} surfels, {len(scene.tags)} tags); trajectory {traj.duration:.1f} s")

    from ghsplat_jax.train.run_dir import raster_settings

    raster = raster_settings(scene.path)  # a trained run's PLY renders with the run's settings
    lidar = None
    if pattern is not None:
        lidar = Lidar(pattern, face_width=args.lidar_face_width, depth=args.lidar_depth, batching=args.lidar_batching,
                      sampling=args.lidar_sampling, raster_config=raster)
    cfg = simulate.SimConfig(camera_rate=args.camera_rate,
                             lidar_rate=(args.lidar_rate if args.lidar_rate is not None else
                                         (pattern.rate_hz if pattern else 0.0)),
                             duration=args.duration, max_events=args.max_events, depth=args.depth,
                             normals=args.normals, organised_cloud=args.organised)
    renderer = CameraRenderer(raster_config=raster)
    sinks = []
    recorder = node = viewer = bar = fox = None
    try:
        if args.record:
            from ghsplat_jax.transport.recorder import BagRecorder

            recorder = BagRecorder(args.record, overwrite=args.overwrite).__enter__()
            sinks.append(lambda topic, msg, t, payload: recorder.write(topic, msg, t))
        if args.live:
            from ghsplat_jax.transport.dds_node import SimNode

            node = SimNode(scene.surfels, domain_id=args.domain_id, localhost_only=not args.any_interface,
                           camera_renderer=renderer, lidar=lidar, lidar_frame=robot.lidar_frame,
                           publish_depth=args.depth, organised_cloud=args.organised)
            sinks.append(node.sink)
            say(f"live on DDS domain {args.domain_id} ({'any interface' if args.any_interface else 'loopback only'})")
        if args.foxglove:
            from ghsplat_jax.transport.foxglove_sink import FoxgloveSink

            fox = FoxgloveSink(host=args.host, port=args.port)
            sinks.append(fox.sink)
            say(f"Foxglove WebSocket at ws://{args.host}:{fox.port}")
        if args.viewer:
            from ghsplat_jax.transport.viewer import SimViewer

            viewer = SimViewer(scene, robot, port=args.viewer_port)
            sinks.append(viewer.sink)
            say(f"viewer at http://localhost:{args.viewer_port}")
        start_wall, counts = time.monotonic(), {}
        bar = tqdm(desc="simulate", unit="frame", disable=args.quiet, dynamic_ncols=True)

        def progress(i, n):
            bar.total = n
            bar.update(i - bar.n)

        for topic, msg, t, payload in simulate.run(scene.surfels, robot, traj, cfg, camera, lidar,
                                                   renderer, progress):
            if (args.live or args.foxglove) and args.real_time > 0:
                simulate.pace(start_wall, cfg.clock_start, t, args.real_time)
            for sink in sinks:
                sink(topic, msg, t, payload)
            if node is not None:
                node.spin_once()  # serve registrations and external camera poses between frames
            counts[topic] = counts.get(topic, 0) + 1
        if node is not None and args.linger > 0:
            node.spin(args.linger)
        elif (viewer is not None or fox is not None) and args.linger > 0:
            time.sleep(args.linger)
    except KeyboardInterrupt:
        say("interrupted")
        if recorder is not None:
            recorder.__exit__(KeyboardInterrupt, None, None)  # discard the partial bag
            recorder = None
        return 130
    finally:
        if bar is not None:
            bar.close()
        if recorder is not None:
            recorder.__exit__(None, None, None)
            say(f"wrote {recorder.path} ({sum(recorder.counts.values())} messages)")
        if node is not None:
            node.close()
        if viewer is not None:
            viewer.close()
        if fox is not None:
            fox.close()
    say("messages: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())) +
        f"; camera compilations {renderer.traces}, LiDAR compilations {lidar.traces if lidar else 0}")
    return 0

