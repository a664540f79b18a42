"""The `etam` command line (DESIGN.md section 8). Every subcommand has --help; errors go to stderr
with a non-zero exit and name what is wrong."""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import threading
import time
from pathlib import Path

from zenoh import ZError

from services import config
from services.camera.formats import FormatError
from services.camera.simulator import DURATION_S as SIM_DURATION_S
from services.camera.sources import SourceError
from services.tracker.ego import MODES as EGO_MODES
from services.tracker.ego import ODOMETRY_MODES, STEREO_WEAK_SHARE
from services.tracker.objects.tracker import DEFAULT_METHOD, METHODS, method_params

log = logging.getLogger("etam")

DEFAULT_CONNECT = "tcp/127.0.0.1:7447"
SOURCE_HELP = ("event source: sim:objects (default), sim:rotation, sim:6dof, sim:stereo (two cameras), "
               "a recording's path, usb (the first iniVation camera) or usb:SERIAL")
USB_BIAS_HELP = ("a USB camera's sensitivity preset: very_low, low, default, high, very_high (DVXplorer); "
                 "low, default, high (DAVIS)")
USB_ROI_HELP = "a USB camera's region of interest X0,Y0,X1,Y1 (inclusive), cropped on the device"
SIM_PARAM_HELP = ("a simulator parameter (repeatable): contrast, contrast_sigma, refractory_us, noise_rate_hz, "
                  "hot_pixel_fraction, hot_pixel_rate_hz, max_step_px, min_dt_us, max_dt_us; the 6dof and stereo "
                  "scenes' IMU: imu_rate_hz, gyro_noise (deg/s/sqrt(Hz)), gyro_bias (deg/s), accel_noise, accel_bias")


def _zenoh_flags(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("zenoh")
    g.add_argument("--connect", action="append", metavar="ENDPOINT",
                   help=f"endpoint to join, e.g. tcp/HOST:7447 (repeatable; env ETAM_CONNECT; "
                        f"default {DEFAULT_CONNECT})")
    g.add_argument("--listen", action="append", metavar="ENDPOINT", help="endpoint to listen on (env ETAM_LISTEN)")
    g.add_argument("--mode", choices=("peer", "client"), help="zenoh mode (env ETAM_MODE; default peer)")
    g.add_argument("--zenoh-config", metavar="FILE", help="zenoh JSON5 config file; flags override it")
    g.add_argument("--multicast", action="store_true", default=None,
                   help="enable multicast scouting (off by default; env ETAM_MULTICAST=1)")
    p.add_argument("--rig", help="rig name in key expressions (env ETAM_RIG; default: host name)")
    p.add_argument("--log-level", default=os.environ.get("ETAM_LOG", "INFO"),
                   choices=("DEBUG", "INFO", "WARNING", "ERROR"))


def _zenoh_settings(args: argparse.Namespace) -> config.ZenohSettings:
    settings = config.resolve(args.mode, args.connect, args.listen, args.multicast, args.zenoh_config)
    if not settings.connect and not settings.listen and not settings.config_file and not settings.multicast:
        settings.connect = [DEFAULT_CONNECT]
    return settings


def _sweep_flags(p: argparse.ArgumentParser, method_default: str) -> None:
    p.add_argument("--method", choices=("sweep", "stereo"), default=None,
                   help="sweep: space sweep of one camera's events (EMVS); stereo: time-surface matching between "
                        f"two cameras (ESVO) (default {method_default})")
    p.add_argument("--depth-range", default="0.5,8", metavar="MIN,MAX",
                   help="nearest and farthest depth it looks at, m (default 0.5,8)")
    p.add_argument("--planes", type=int, default=100, help="depth planes of the sweep (default 100)")


def _mosaic_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument("--size", default="2048x1024", metavar="WxH",
                   help="equirectangular panorama size, pixels (default 2048x1024)")
    p.add_argument("--contrast", type=float, default=0.25,
                   help="the sensor's contrast threshold C, log intensity per event (default 0.25)")
    p.add_argument("--fit-iterations", type=int, default=20, metavar="N",
                   help="iterations fitting the mosaic to the events' own brightness steps (default 20; 0: the "
                        "gradient filter's Poisson reconstruction alone)")


def _mosaic_params(args: argparse.Namespace):  # noqa: ANN202 - MosaicParams
    """The mosaic's settings from `--size`, `--contrast` and `--fit-iterations`; ConfigError naming a bad one."""
    from services.mapper.mosaic import MosaicParams

    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        raise config.ConfigError(f"--size takes WxH in pixels, e.g. 2048x1024, got {args.size!r}") from None
    if width < 8 or height < 4 or args.contrast <= 0 or args.fit_iterations < 0:
        raise config.ConfigError(f"--size needs at least 8x4 (got {args.size}), --contrast > 0 (got {args.contrast}) "
                                 f"and --fit-iterations >= 0 (got {args.fit_iterations})")
    return MosaicParams(width=width, height=height, contrast=args.contrast, fit_iterations=args.fit_iterations)


def _service_options(args: argparse.Namespace, kind: str):  # noqa: ANN202 - ServiceOptions
    from services.runtime import ServiceOptions

    return ServiceOptions(rig=config.resolve_rig(args.rig), name=args.name or kind, zenoh=_zenoh_settings(args))


def _usb_options(args: argparse.Namespace) -> dict:
    """`--usb-bias` and `--usb-roi` as the USB source takes them; ConfigError naming a bad ROI."""
    out: dict = {"bias": args.usb_bias or "default"}
    if args.usb_roi:
        try:
            x0, y0, x1, y1 = (int(v) for v in args.usb_roi.split(","))
        except ValueError:
            raise config.ConfigError(f"--usb-roi takes X0,Y0,X1,Y1 in pixels, got {args.usb_roi!r}") from None
        if not (0 <= x0 <= x1 and 0 <= y0 <= y1):
            raise config.ConfigError(f"--usb-roi needs 0 <= X0 <= X1 and 0 <= Y0 <= Y1, got {args.usb_roi}")
        out["roi"] = (x0, y0, x1, y1)
    return out


def _cmd_camera(args: argparse.Namespace) -> int:
    from services.camera.service import CameraService
    from services.camera.sources import open_sources

    if args.rate < 0:
        raise config.ConfigError(f"--rate must be >= 0 (0: as fast as possible), got {args.rate}")
    from services.camera.filters import parse_chain
    from services.camera.simulator import SimParams

    params = SimParams.parse(args.sim_param or [])
    sources = open_sources(args.source, seed=args.seed, loop=args.loop, sim_params=params, usb=_usb_options(args))
    chains = [parse_chain(args.filter or [], src.width, src.height, src.K,
                          src.calibration.dist_model if src.calibration else "none",
                          src.calibration.dist if src.calibration else None) for src in sources]
    opts = _service_options(args, "cam0")
    return CameraService(opts, sources, slice_us=args.slice_us, max_events=args.max_events, rate=args.rate,
                         filters=chains).run()


def _cmd_tracker(args: argparse.Namespace) -> int:
    from services.tracker.service import ObjectSizes, TrackerService

    try:
        sizes = ObjectSizes.parse(args.object_size or [])
    except ValueError as exc:
        raise config.ConfigError(str(exc)) from None
    if not 0 <= args.map_refresh < 1:
        raise config.ConfigError(f"--map-refresh must be in [0, 1), got {args.map_refresh}")
    from services.tracker.ego.loop import RefreshParams

    return TrackerService(_service_options(args, "objects"), method_params(args.method), cam=args.cam,
                          sizes=sizes, ego=args.ego, refresh=RefreshParams(weak_share=args.map_refresh)).run()


def _cmd_mapper(args: argparse.Namespace) -> int:
    from services.mapper.service import MapperService
    from services.tracker.ego.loop import tracking_map

    params = tracking_map(_map_params(args), args.method == "stereo") if args.tracking_map else _map_params(args)
    try:
        service = MapperService(_service_options(args, "map"), params, cam=args.cam, poses=args.poses,
                                mode=args.build, mosaic_params=_mosaic_params(args), method=args.method or "sweep",
                                right=args.right, max_rate=args.max_rate * 1e6)
    except ValueError as exc:
        raise config.ConfigError(str(exc)) from None
    return service.run()


def _cmd_web(args: argparse.Namespace) -> int:
    from web.service import WebService

    return WebService(_service_options(args, "web"), host=args.host, port=args.port).run()


# sources the mapper maps in `etam up`, and its flags: with the simulator's truth poses, but the spinning camera's
# mosaic from the tracker's own rotation estimates (see EGO_SIMS), closing the loop; the live mosaic at half
# size: its Poisson solve costs a fifth, leaving the cores to the camera
MAPPED_SIMS = {"sim:6dof": (), "sim:stereo": ("--method", "stereo"),
               "sim:rotation": ("--build", "mosaic", "--size", "1024x512", "--poses", "ego")}
# sources whose tracker also estimates the camera's motion in `etam up` (unless --ego says otherwise), and how. With
# --ego 6dof the mapper maps from the tracker's poses, and the tracker follows its map: the closed loop; it is not
# sim:6dof's default, whose map comes from the truth, as it still drifts and loses its map live (see the README)
EGO_SIMS = {"sim:rotation": "rotation"}
LOOP_MAPPER_ARGS = ("--poses", "ego", "--tracking-map")


def _cmd_up(args: argparse.Namespace) -> int:
    from services.launcher import UpOptions, up

    if args.duration is not None and args.duration <= 0:
        raise config.ConfigError(f"--duration must be positive, got {args.duration}")
    ego = args.ego or EGO_SIMS.get(args.source, "off")
    mapped = args.source in MAPPED_SIMS or args.map or ego == "6dof"
    opts = UpOptions(
        rig=config.resolve_rig(args.rig), source=args.source, listen=args.listen, web=not args.no_web,
        web_port=args.web_port, duration_s=args.duration, report=Path(args.report) if args.report else None,
        log_level=args.log_level,
        services=("camera", "tracker", *(("mapper",) if mapped else ())),
        mapper_args=(*MAPPED_SIMS.get(args.source, ()), *(LOOP_MAPPER_ARGS if ego == "6dof" else ())),
        camera_args=("--rate", str(args.rate), *(("--loop",) if args.loop else ()),
                     *(a for f in args.filter or [] for a in ("--filter", f)),
                     *(a for item in args.sim_param or [] for a in ("--sim-param", item)),
                     *(("--usb-bias", args.usb_bias) if args.usb_bias else ()),
                     *(("--usb-roi", args.usb_roi) if args.usb_roi else ())),
    )
    from services.camera.simulator import SimParams
    from services.camera.sources import open_sources

    SimParams.parse(args.sim_param or [])  # a bad simulator parameter fails here, before anything starts

    if args.rate < 0:
        raise config.ConfigError(f"--rate must be >= 0 (0: as fast as possible), got {args.rate}")
    from services.camera.filters import parse_chain

    # a bad source or filter fails here, before anything starts
    sources = open_sources(args.source, usb=_usb_options(args))
    for src in sources:  # a USB camera is released again for the camera service to open
        getattr(src, "close", lambda: None)()
    parse_chain([f for f in args.filter or [] if f != "undistort"], sources[0].width, sources[0].height)
    recording = getattr(sources[0], "recording", None)
    if args.map and args.source not in MAPPED_SIMS and (recording is None or recording.truth.poses is None):
        raise config.ConfigError(f"--map: {args.source} has no truth poses to map with (a recording with "
                                 "/truth/poses, or sim:6dof, sim:stereo, sim:rotation)")
    if ego == "6dof" and args.source not in MAPPED_SIMS and (recording is None or recording.truth.poses is None):
        raise config.ConfigError(f"--ego 6dof: {args.source} has no known poses to start from (a recording with "
                                 "/truth/poses, or sim:6dof, sim:stereo)")
    if len(sources) > 1:  # a rig: boxes of the first camera (Tracks carry no camera, so one camera per tracker)
        opts.tracker_args = ("--cam", "cam0")
        if "--method" not in opts.mapper_args:  # mapped by stereo, as `etam map` maps a file of two cameras
            opts.mapper_args += ("--method", "stereo")
    if ego != "off":
        opts.tracker_args += ("--ego", ego)
    if ego == "6dof" and "stereo" in opts.mapper_args:  # the loop's keyframes when its map fails it (see loop_params)
        opts.tracker_args += ("--map-refresh", str(STEREO_WEAK_SHARE))
    return up(opts)


def _cmd_router(args: argparse.Namespace) -> int:
    import zenoh

    default_listen = [] if args.zenoh_config else ["tcp/0.0.0.0:7447"]
    settings = config.resolve("router", None, args.listen or default_listen, None, args.zenoh_config)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    with zenoh.open(settings.zenoh_config()):
        log.info("zenoh router listening on %s", ", ".join(settings.listen) or f"the endpoints of {args.zenoh_config}")
        stop.wait()
    return 0


def _positive_int(text: str) -> int:
    """An argparse type: a whole number above 0, or a message that names what was given."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number above 0")
    return value


def _output(path: str) -> Path:
    """A file a command will write, checked before the work: a missing folder is named at once, not
    after minutes of tracking or simulating."""
    out = Path(path)
    if not out.parent.is_dir():
        raise config.ConfigError(f"{out}: folder {out.parent} does not exist")
    return out


def _open_session(args: argparse.Namespace):  # noqa: ANN202 - zenoh.Session
    import zenoh

    return zenoh.open(_zenoh_settings(args).zenoh_config())


def _cmd_ls(args: argparse.Namespace) -> int:
    from services.introspect import format_services, list_services

    with _open_session(args) as session:
        found = list_services(session, args.rig or "*", args.wait)
    print(json.dumps(found, indent=2) if args.json else format_services(found))
    return 0


def _cmd_echo(args: argparse.Namespace) -> int:
    from services.introspect import echo

    with _open_session(args) as session:
        n = echo(session, args.keyexpr, sys.stdout, args.count, args.timeout, args.full)
    if args.count is not None and n < args.count:
        print(f"etam echo: got {n} of {args.count} messages on {args.keyexpr} in {args.timeout} s", file=sys.stderr)
        return 1
    return 0


def _cmd_hz(args: argparse.Namespace) -> int:
    from services.introspect import hz

    with _open_session(args) as session:
        hz(session, args.keyexpr, sys.stdout, args.period, args.reports, args.json)
    return 0


def _cmd_sim(args: argparse.Namespace) -> int:
    from services.camera.offline import simulate

    if args.duration <= 0:
        raise config.ConfigError(f"--duration must be positive, got {args.duration}")
    from services.camera.simulator import SimParams

    params = SimParams.parse(args.sim_param or [])
    scene_args = None
    if args.peak is not None:
        if args.scene != "rotation" or args.peak <= 0:
            raise config.ConfigError(f"--peak (deg/s, > 0) sets the rotation scene's peak speed, got {args.peak} "
                                     f"for scene {args.scene}")
        scene_args = {"peak_deg_s": args.peak}
    summary = simulate(args.scene, _output(args.out), args.duration, args.seed, progress=not args.json, params=params,
                       scene_args=scene_args)
    print(json.dumps(summary) if args.json else f"wrote {summary['events']} events of sim:{args.scene} "
          f"({args.duration} s, seed {args.seed}), {summary['truth_boxes']} truth boxes, "
          f"{summary['truth_poses']} truth poses and {summary['imu_samples']} IMU samples to {args.out}")
    return 0


def _cmd_info(args: argparse.Namespace) -> int:
    from services.camera.offline import describe

    facts = describe(Path(args.file), progress=not args.json)
    if args.json:
        print(json.dumps(facts))
    else:
        for k, v in facts.items():
            print(f"{k:>14}: {v}")
    return 0


def _cmd_track(args: argparse.Namespace) -> int:
    from services.tracker.offline import track

    if not Path(args.input).exists():
        raise config.ConfigError(f"{args.input}: no such file")
    out, shots = _output(args.out), _output(args.snapshots) if args.snapshots else None
    summary = track(Path(args.input), out, method_params(args.method), progress=not args.json)
    if shots is not None:
        from services.tracker.offline import read_tracks, snapshots

        snapshots(Path(args.input), read_tracks(out), shots)
        summary["snapshots"] = args.snapshots
    print(json.dumps(summary) if args.json else f"wrote {summary['boxes']} boxes of {summary['track_ids']} tracks "
          f"({summary['updates']} updates, {summary['events']} events) to {args.out}")
    return 0


def _map_params(args: argparse.Namespace):  # noqa: ANN202 - KeyframeParams
    """The sweep's settings from `--depth-range` and `--planes`; ConfigError naming a bad one."""
    from services.mapper.keyframes import KeyframeParams
    from services.mapper.sweep import SweepParams

    try:
        near, far = (float(v) for v in args.depth_range.split(","))
    except ValueError:
        raise config.ConfigError(f"--depth-range takes MIN,MAX in metres, got {args.depth_range!r}") from None
    if not 0 < near < far or args.planes < 3:
        raise config.ConfigError(f"--depth-range needs 0 < MIN < MAX (got {args.depth_range}) and --planes >= 3 "
                                 f"(got {args.planes})")
    return KeyframeParams(SweepParams(planes=args.planes, z_min_m=near, z_max_m=far))


def _require_files(*paths: str | None) -> None:
    """Input files checked before the work starts (None: an optional one not given)."""
    for path in paths:
        if path and not Path(path).exists():
            raise config.ConfigError(f"{path}: no such file")


def _cmd_map(args: argparse.Namespace) -> int:
    from services.mapper.offline import build_map

    _require_files(args.input, args.poses)
    summary = build_map(Path(args.input), _output(args.out), Path(args.poses) if args.poses else None,
                        _map_params(args), progress=not args.json, method=args.method)
    print(json.dumps(summary) if args.json else f"wrote {summary['points']} map points from {summary['keyframes']} "
          f"keyframes ({summary['method']}, {summary['events']} events, {summary['poses']} poses) to {args.out}")
    return 0


def _cmd_mosaic(args: argparse.Namespace) -> int:
    from services.mapper.offline import build_mosaic

    _require_files(args.input, args.poses)
    summary = build_mosaic(Path(args.input), _output(args.out), Path(args.poses) if args.poses else None,
                           _mosaic_params(args), progress=not args.json)
    print(json.dumps(summary) if args.json else f"wrote a {summary['size'][0]}x{summary['size'][1]} mosaic "
          f"({summary['observed']:.0%} observed) from {summary['events']} events ({summary['poses']} poses) "
          f"to {args.out}")
    return 0


def _cmd_eval_mosaic(args: argparse.Namespace) -> int:
    from services.mapper.offline import eval_mosaic

    _require_files(args.mosaic, args.truth)
    scores = eval_mosaic(Path(args.mosaic), Path(args.truth))
    print(json.dumps(scores)) if args.json else _print_scores(scores)
    return 0


def _print_scores(scores: dict) -> None:
    for k, v in scores.items():
        if isinstance(v, dict):  # counts by kind, say
            v = ", ".join(f"{name} {n}" for name, n in v.items())
        print(f"{k:>30}: {v:.3f}" if isinstance(v, float) else f"{k:>30}: {v}")


def _cmd_odom(args: argparse.Namespace) -> int:
    from services.tracker.offline import odometry

    _require_files(args.input, *([args.start] if args.start else []))
    summary = odometry(Path(args.input), _output(args.out), progress=not args.json, mode=args.mode,
                       bootstrap_s=args.bootstrap, start=Path(args.start) if args.start else None, method=args.method,
                       imu=not args.no_imu)
    detail = (f"{summary['still']} still" if args.mode == "rotation" else
              f"{summary['keyframes']} keyframes, first map from {summary['bootstrap_s']:g} s of known poses"
              + (", rotation from the gyro" if summary["gyro"] else ""))
    print(json.dumps(summary) if args.json else f"wrote {summary['poses']} poses ({summary['mode']}, {detail}, "
          f"{summary['lost']} lost, {summary['events']} events) to {args.out}")
    return 0


def _cmd_eval_odometry(args: argparse.Namespace) -> int:
    from services.tracker.offline import eval_odometry

    _require_files(args.pred, args.truth)
    scores = eval_odometry(Path(args.pred), Path(args.truth), args.align)
    print(json.dumps(scores)) if args.json else _print_scores(scores)
    return 0


def _cmd_eval_map(args: argparse.Namespace) -> int:
    from services.mapper.offline import eval_map

    _require_files(args.cloud, args.truth)
    scores = eval_map(Path(args.cloud), Path(args.truth))
    print(json.dumps(scores)) if args.json else _print_scores(scores)
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    from services.tracker.offline import eval_tracking, read_tracks, switch_snapshots

    scores = eval_tracking(Path(args.pred), Path(args.truth))
    if args.snapshots:
        drawn = switch_snapshots(Path(args.truth), read_tracks(Path(args.pred)), scores["id_switch_events"],
                                 _output(args.snapshots), args.most)
        scores["snapshots"] = {"file": args.snapshots if drawn else None, "switches_drawn": drawn}
    if args.json:
        print(json.dumps(scores))
        return 0
    events = scores.pop("id_switch_events")
    shots = scores.pop("snapshots", None)
    _print_scores(scores)
    for e in events:  # where to look: the time, the truth object, the track ids before and after
        print(f"{'id switch':>30}: {e['t_us'] / 1e6:.3f} s, object {e['object']}: track {e['from_id']} -> {e['to_id']}"
              f" ({e['cause']})")
    if shots is not None:
        print(f"drew the first {shots['switches_drawn']} id switches into {args.snapshots}" if shots["file"]
              else "no id switches to draw")
    return 0


def _cmd_convert(args: argparse.Namespace) -> int:
    from services.camera.offline import convert

    summary = convert(Path(args.input), _output(args.output), progress=not args.json)
    print(json.dumps(summary) if args.json else f"wrote {summary['events']} events of {args.input} "
          f"({summary['input_format']}) to {args.output}")
    return 0


def _cmd_devices(args: argparse.Namespace) -> int:
    from services.camera.usb.driver import UsbError, backend, discover

    try:
        found = discover(backend())
    except UsbError as exc:
        raise config.ConfigError(str(exc)) from None
    if args.json:
        print(json.dumps([d.as_dict() for d in found]))
    elif not found:
        print("no iniVation camera found on USB")
    for d in found if not args.json else ():
        size = f"{d.width}x{d.height}" if d.width else "?"
        print(f"{d.model} serial {d.serial} ({size}, firmware {d.firmware}, logic {d.logic_version}.{d.logic_patch}, "
              f"USB {d.usb_speed}, bus {d.bus} address {d.address}): "
              + (d.problem or f"ready, open it with --source usb:{d.serial}"))
    return 0


def _cmd_usb_decode(args: argparse.Namespace) -> int:
    from services.camera.usb.dump import decode_dump

    summary = decode_dump(args.model, Path(args.dump), _output(args.out), progress=not args.json)
    print(json.dumps(summary) if args.json else f"wrote {summary['events']} events ({summary['imu_samples']} IMU "
          f"samples, {summary['timestamp_resets']} timestamp resets, {summary['dropped_words']} words dropped) "
          f"of {args.dump} to {args.out}")
    return 0


def _cmd_record(args: argparse.Namespace) -> int:
    from services.camera.recorder import RecordService

    return RecordService(_service_options(args, "recorder"), _output(args.out), args.keys).run()


def _cmd_replay(args: argparse.Namespace) -> int:
    from services.camera.recorder import ReplayService

    path = Path(args.file)
    if not path.is_file():
        raise config.ConfigError(f"{path}: no such file")
    if args.rate < 0:
        raise config.ConfigError(f"--rate must be >= 0 (0: as fast as possible), got {args.rate}")
    return ReplayService(_service_options(args, "replay"), path, args.rate, args.loop).run()


def _cmd_bench(args: argparse.Namespace) -> int:
    from benchmarks import suite

    results = suite.run(quick=args.quick, only=args.only)
    print(json.dumps(results, indent=2) if args.json else suite.format_results(results))
    return 0


def _cmd_warmup(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from services.kernels import PARTS

    took = {}
    with tqdm(PARTS.items(), unit="part", disable=args.json) as bar:
        for name, warm_up in bar:
            bar.set_description(name)
            start = time.perf_counter()
            warm_up()
            took[name] = round(time.perf_counter() - start, 2)
    print(json.dumps({"parts": took, "seconds": round(sum(took.values()), 2)}) if args.json else
          "kernels loaded (and cached for every later run): "
          + ", ".join(f"{name} {seconds:.1f} s" for name, seconds in took.items()))
    return 0


METHOD_HELP = ("tracking method: contour (default; decayed image, occupancy clusters), adaptive (time/count "
               "window chosen by frame quality), camshift (CamShift on edges), corner (corner clusters), "
               "keyevents (contour on key events)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="etam", description="ETAM: event-based tracking and mapping.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("up", help="run the whole rig (router, camera, tracker, dashboard)")
    p.add_argument("--source", default="sim:objects", help=SOURCE_HELP)
    p.add_argument("--rate", type=float, default=1.0, help="playback speed of a recording (0: as fast as possible)")
    p.add_argument("--loop", action="store_true", help="play a recording again and again")
    p.add_argument("--filter", action="append", metavar="NAME[:ARGS]", help="camera filter chain (see etam camera)")
    p.add_argument("--sim-param", action="append", metavar="NAME=VALUE", help=SIM_PARAM_HELP)
    p.add_argument("--usb-bias", metavar="PRESET", help=USB_BIAS_HELP)
    p.add_argument("--usb-roi", metavar="X0,Y0,X1,Y1", help=USB_ROI_HELP)
    p.add_argument("--rig", help="rig name (env ETAM_RIG; default: host name)")
    p.add_argument("--listen", default="tcp/0.0.0.0:7447", help="router endpoint (default tcp/0.0.0.0:7447)")
    p.add_argument("--web-port", type=int, default=8080, help="dashboard port (default 8080)")
    p.add_argument("--no-web", action="store_true", help="do not start the dashboard")
    p.add_argument("--map", action="store_true",
                   help="also run the mapper on a recording's truth poses (the simulator's 3D scenes map anyway)")
    p.add_argument("--ego", choices=EGO_MODES,
                   help="the camera's motion the tracker estimates: rotation, 6dof (the closed loop: the mapper maps "
                        "from the tracker's poses, the tracker follows its map, started from the source's truth "
                        "poses) or off; default rotation for sim:rotation, else off")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds and exit 0")
    p.add_argument("--report", metavar="FILE.json", help="write per-key and per-service counts at the end")
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    p.set_defaults(func=_cmd_up)

    p = sub.add_parser("router", help="run a zenoh router alone (for systemd deployments)")
    p.add_argument("--listen", action="append", metavar="ENDPOINT", help="default tcp/0.0.0.0:7447")
    p.add_argument("--zenoh-config", metavar="FILE", help="zenoh JSON5 config file")
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    p.set_defaults(func=_cmd_router)

    p = sub.add_parser("camera", help="run the camera service alone")
    _zenoh_flags(p)
    p.add_argument("--name", help="camera name in keys (default cam0)")
    p.add_argument("--source", default="sim:objects", help=SOURCE_HELP)
    p.add_argument("--rate", type=float, default=1.0,
                   help="playback speed of a recording: 1 real time (default), 2 twice as fast, 0 as fast as possible")
    p.add_argument("--loop", action="store_true", help="play a recording again and again")
    p.add_argument("--filter", action="append", metavar="NAME[:ARGS]",
                   help="add a filter to the chain, in order: ba[:WINDOW_US], refractory[:US], roi:X,Y,W,H, "
                        "mask:IMAGE.png, polarity:on|off, hotpixels[:LEARN_US], undistort")
    p.add_argument("--seed", type=int, default=0, help="simulator seed")
    p.add_argument("--sim-param", action="append", metavar="NAME=VALUE", help=SIM_PARAM_HELP)
    p.add_argument("--usb-bias", metavar="PRESET", help=USB_BIAS_HELP)
    p.add_argument("--usb-roi", metavar="X0,Y0,X1,Y1", help=USB_ROI_HELP)
    p.add_argument("--slice-us", type=int, default=1000, help="packet time slice in us (default 1000)")
    p.add_argument("--max-events", type=int, default=100_000, help="largest packet (default 100000)")
    p.set_defaults(func=_cmd_camera)

    p = sub.add_parser("tracker", help="run the object tracker service alone")
    _zenoh_flags(p)
    p.add_argument("--name", help="tracker name in keys (default objects)")
    p.add_argument("--method", default=DEFAULT_METHOD, choices=tuple(METHODS), help=METHOD_HELP)
    p.add_argument("--cam", default="*",
                   help="the camera whose events it tracks (default *: every camera; their tracks share one key, so "
                        "a rig of several cameras is better served by one tracker per camera, each with --name)")
    p.add_argument("--ego", default="off", choices=EGO_MODES,
                   help="camera ego-motion on tracker/ego/pose: rotation (a turning camera: angular velocity by "
                        "contrast maximisation, tracked against a panoramic map of the events); 6dof (the pose, by "
                        "aligning the mapper's map, built from these poses, to the events: run a mapper with --poses "
                        "ego --tracking-map; the camera's truth/pose starts it); or off (default)")
    p.add_argument("--map-refresh", type=float, default=0.0, metavar="SHARE",
                   help="with --ego 6dof: ask the mapper for a keyframe once the estimates explain under SHARE of "
                        "their best inlier share since the last one, and when lost (0: never, the default; for a "
                        f"stereo mapper, whose depth needs no travel, etam up gives {STEREO_WEAK_SHARE})")
    p.add_argument("--object-size", action="append", metavar="[ID=]M",
                   help="known width of targets in metres, for their 3D position (xyz = f * size / pixels): "
                        "M for every target, ID=M for one track id; repeatable")
    p.set_defaults(func=_cmd_tracker)

    p = sub.add_parser("mapper", help="run the mapper service alone (semi-dense map from events and poses)")
    _zenoh_flags(p)
    p.add_argument("--name", help="mapper name in keys (default map)")
    p.add_argument("--cam", default="cam0", help="the camera whose events it maps (default cam0)")
    p.add_argument("--poses", default="ego", choices=("ego", "truth"),
                   help="camera poses: the tracker's ego pose (default), or the camera's truth pose (simulator)")
    p.add_argument("--build", default="depth", choices=("depth", "mosaic"),
                   help="what to build: depth, a semi-dense 3D map (default); mosaic, the panorama of a rotating "
                        "camera (on mapper/map/mosaic)")
    p.add_argument("--right", default="cam1", help="with --method stereo: the right camera of the pair (default cam1)")
    p.add_argument("--max-rate", type=float, default=0.4, metavar="MEV_S",
                   help="the sweep takes at most this many million events per second of stream, every k-th "
                        "(so that it keeps up with the camera on few cores; 0: all; default 0.4)")
    _sweep_flags(p, "sweep")
    p.add_argument("--tracking-map", action="store_true",
                   help="a denser map, for a tracker --ego 6dof to follow: weaker peaks kept, seen with 10 px of "
                        "parallax, not 20 (etam odom --mode 6dof's)")
    _mosaic_flags(p)
    p.set_defaults(func=_cmd_mapper)

    p = sub.add_parser("web", help="run the dashboard service alone")
    _zenoh_flags(p)
    p.add_argument("--name", help="name in keys (default web)")
    p.add_argument("--host", default="0.0.0.0", help="address to serve on (default all)")
    p.add_argument("--port", type=int, default=8080, help="dashboard port (default 8080)")
    p.set_defaults(func=_cmd_web)

    p = sub.add_parser("ls", help="list live services and their keys with rates")
    _zenoh_flags(p)
    p.add_argument("--wait", type=float, default=1.5, help="seconds to listen for Stats (default 1.5)")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=_cmd_ls)

    p = sub.add_parser("echo", help="print the messages on a key expression as JSON lines")
    _zenoh_flags(p)
    p.add_argument("keyexpr", help="e.g. 'etam/*/tracker/objects/tracks'")
    p.add_argument("--count", type=int, help="exit after N messages")
    p.add_argument("--timeout", type=float, help="exit after S seconds")
    p.add_argument("--full", action="store_true", help="print arrays in full (default: up to 8 values, then a summary)")
    p.set_defaults(func=_cmd_echo)

    p = sub.add_parser("hz", help="print message and event rates on a key expression")
    _zenoh_flags(p)
    p.add_argument("keyexpr", help="e.g. 'etam/*/camera/*/events'")
    p.add_argument("--period", type=float, default=1.0, help="seconds between reports")
    p.add_argument("--reports", type=int, help="exit after N reports")
    p.add_argument("--json", action="store_true", help="one JSON object per report")
    p.set_defaults(func=_cmd_hz)

    p = sub.add_parser("sim", help="simulate a scene into an ETAM HDF5 file with ground truth (and, for 6dof and "
                                   "stereo, the moving camera's IMU)")
    p.add_argument("scene", choices=("objects", "rotation", "6dof", "stereo"), help="scene to simulate")
    p.add_argument("--out", required=True, metavar="FILE.h5", help="output file")
    p.add_argument("--duration", type=float, default=SIM_DURATION_S, metavar="S",
                   help=f"seconds (default {SIM_DURATION_S:g})")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--sim-param", action="append", metavar="NAME=VALUE", help=SIM_PARAM_HELP)
    p.add_argument("--peak", type=float, metavar="DEG_S", help="rotation only: the motion scaled to peak at this "
                                                               "angular speed (default: 616 deg/s)")
    p.add_argument("--json", action="store_true", help="print a JSON summary, no progress bar")
    p.set_defaults(func=_cmd_sim)

    p = sub.add_parser("track", help="track moving objects in a recording into a CSV (t_us,id,x,y,w,h,score)")
    p.add_argument("input", help="any readable event file")
    p.add_argument("--out", default="tracks.csv", help="tracks CSV to write (default tracks.csv)")
    p.add_argument("--method", default=DEFAULT_METHOD, choices=tuple(METHODS), help=METHOD_HELP)
    p.add_argument("--snapshots", metavar="FILE.png", help="also draw the boxes on six event frames into a PNG")
    p.add_argument("--json", action="store_true", help="print a JSON summary instead of a progress bar")
    p.set_defaults(func=_cmd_track)

    p = sub.add_parser("odom", help="camera motion of a recording into a TUM trajectory (t tx ty tz qx qy qz qw, "
                                    "T_world_cam): its orientation, or its 6-DoF pose with a map built on the way")
    p.add_argument("input", help="any readable event file")
    p.add_argument("--mode", default="rotation", choices=ODOMETRY_MODES,
                   help="rotation: angular velocity by contrast maximisation, integrated (a turning camera); 6dof: "
                        "the semi-dense map aligned to the events, the map swept from those poses (default rotation)")
    p.add_argument("--bootstrap", type=float, default=1.5, metavar="S",
                   help="6dof: seconds of known poses at the start, whose events make the first map (default 1.5)")
    p.add_argument("--start", metavar="TRAJ.tum",
                   help="6dof: the known poses of the start (TUM, T_world_cam); default: the file's truth poses")
    p.add_argument("--method", choices=("sweep", "stereo"), default=None,
                   help="6dof: how the map is built: sweep, the space sweep of the first camera's events (EMVS); "
                        "stereo, time-surface matching between the first two cameras (ESVO) (default: stereo for "
                        "a file of two cameras, else sweep)")
    p.add_argument("--no-imu", action="store_true",
                   help="6dof: leave the file's gyro out (by default, where the file has IMU samples, the gyro "
                        "predicts each update's rotation and its bias is learnt on the way)")
    p.add_argument("--out", default="traj.tum", help="TUM trajectory to write (default traj.tum)")
    p.add_argument("--json", action="store_true", help="print a JSON summary instead of a progress bar")
    p.set_defaults(func=_cmd_odom)

    p = sub.add_parser("map", help="semi-dense 3D map of a recording (EMVS space sweep, or ESVO stereo for two "
                                   "cameras) into a PLY point cloud")
    p.add_argument("input", help="any readable event file")
    p.add_argument("--poses", metavar="TRAJ.tum", help="camera poses (TUM: t tx ty tz qx qy qz qw, T_world_cam); "
                                                        "default: the file's truth poses")
    p.add_argument("--out", default="cloud.ply", help="PLY to write (default cloud.ply)")
    _sweep_flags(p, "stereo for a file of two cameras, such as etam sim stereo writes; else sweep")
    p.add_argument("--json", action="store_true", help="print a JSON summary instead of a progress bar")
    p.set_defaults(func=_cmd_map)

    p = sub.add_parser("mosaic", help="panoramic mosaic of a rotating camera's recording (gradient EKF per "
                                      "panorama pixel, Poisson reconstruction) into a 16-bit PNG")
    p.add_argument("input", help="any readable event file")
    p.add_argument("--poses", metavar="TRAJ.tum", help="camera orientations (TUM: t tx ty tz qx qy qz qw, "
                                                        "T_world_cam); default: the file's truth poses")
    p.add_argument("--out", default="mosaic.png", help="PNG to write (default mosaic.png; 0 = never observed)")
    _mosaic_flags(p)
    p.add_argument("--json", action="store_true", help="print a JSON summary instead of a progress bar")
    p.set_defaults(func=_cmd_mosaic)

    p = sub.add_parser("eval", help="score results against ground truth")
    kinds = p.add_subparsers(dest="kind", required=True, metavar="KIND")
    q = kinds.add_parser("tracking", help="OP50/OP75, success AUC, precision@20, false positives, id switches "
                                          "(each listed with its time, object and ids), MOTA, IDF1")
    q.add_argument("--pred", required=True, help="tracks CSV from etam track")
    q.add_argument("--truth", required=True, help="a recording with /truth/boxes (e.g. from etam sim objects)")
    q.add_argument("--snapshots", metavar="FILE.png", help="also draw each id switch (the event frames 0.2 s "
                                                           "before it and at it, truth and tracked boxes) into a PNG")
    q.add_argument("--most", type=_positive_int, default=8, help="switches drawn at most (default 8)")
    q.add_argument("--json", action="store_true", help="machine-readable output")
    q.set_defaults(func=_cmd_eval)
    q = kinds.add_parser("map", help="depth errors of a map's points against truth depth (mean, median, share "
                                     "within 5 %%), and the share of truth edge pixels it covers")
    q.add_argument("--cloud", required=True, help="PLY map from etam map")
    q.add_argument("--truth", required=True, help="a recording with /truth/depth and /truth/poses (etam sim 6dof)")
    q.add_argument("--json", action="store_true", help="machine-readable output")
    q.set_defaults(func=_cmd_eval_map)
    q = kinds.add_parser("odometry", help="ATE after alignment, RPE per second, angular velocity error (evo)")
    q.add_argument("--pred", required=True, help="TUM trajectory from etam odom")
    q.add_argument("--truth", required=True, help="a recording with /truth/poses (etam sim rotation), or a TUM "
                                                  "ground truth file (.txt or .tum, e.g. an ECD groundtruth.txt)")
    q.add_argument("--align", default="auto", choices=("auto", "se3", "sim3", "origin"),
                   help="auto (default): se3 (Umeyama) if the truth moves, else origin (first poses made equal)")
    q.add_argument("--json", action="store_true", help="machine-readable output")
    q.set_defaults(func=_cmd_eval_odometry)
    q = kinds.add_parser("mosaic", help="PSNR and SSIM of a mosaic against the truth panorama (log intensity, "
                                        "observed pixels, after removing offset and scale)")
    q.add_argument("--mosaic", required=True, help="PNG from etam mosaic")
    q.add_argument("--truth", required=True, help="a recording with /truth/panorama (etam sim rotation)")
    q.add_argument("--json", action="store_true", help="machine-readable output")
    q.set_defaults(func=_cmd_eval_mosaic)

    p = sub.add_parser("info", help="sensor size, events, duration, rate, polarity, IMU and truth of a file")
    p.add_argument("file", help="an event file or ECD folder")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=_cmd_info)

    p = sub.add_parser("convert", help="convert a recording to ETAM HDF5 (.h5), AEDAT 4.0 (.aedat4) or ECD text")
    p.add_argument("input", help="any readable event file or ECD folder")
    p.add_argument("output", help="FILE.h5, FILE.aedat4, events.txt, or a folder for ECD text")
    p.add_argument("--json", action="store_true", help="print a JSON summary, no progress bar")
    p.set_defaults(func=_cmd_convert)

    p = sub.add_parser("devices", help="list the iniVation USB cameras plugged in (model, serial, versions, "
                       "USB speed, permission problems)")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=_cmd_devices)

    p = sub.add_parser("usb-decode", help="decode a raw dump of a camera's USB bulk stream into an event file")
    p.add_argument("dump", metavar="DUMP.bin", help="the bytes read from the camera's bulk endpoint 0x82")
    p.add_argument("--model", required=True, choices=("dvxplorer", "dvxplorer-lite", "davis346", "davis240"),
                   help="the camera the dump came from (its word layout and sensor size)")
    p.add_argument("--out", required=True, metavar="EVENTS.h5", help="output ETAM HDF5 file")
    p.add_argument("--json", action="store_true", help="print a JSON summary, no progress bar")
    p.set_defaults(func=_cmd_usb_decode)

    p = sub.add_parser("record", help="record live messages to an MCAP file (lossless; Ctrl-C to stop)")
    _zenoh_flags(p)
    p.add_argument("out", metavar="OUT.mcap", help="output file")
    p.add_argument("--keys", default="etam/**", help="key expression to record (default etam/**)")
    p.add_argument("--name", help="name in keys (default recorder)")
    p.set_defaults(func=_cmd_record)

    p = sub.add_parser("replay", help="publish an MCAP recording again, byte for byte")
    _zenoh_flags(p)
    p.add_argument("file", metavar="IN.mcap", help="a recording made by etam record")
    p.add_argument("--rate", type=float, default=1.0, help="speed: 1 original timing (default), 0 as fast as possible")
    p.add_argument("--loop", action="store_true", help="start over at the end")
    p.add_argument("--name", help="name in keys (default replay)")
    p.set_defaults(func=_cmd_replay)

    p = sub.add_parser("bench", help="run the performance suite")
    p.add_argument("--json", action="store_true", help="machine-readable results on stdout")
    p.add_argument("--quick", action="store_true", help="shorter runs (for smoke tests)")
    p.add_argument("--only", action="append", help="run only these benchmarks (e.g. transport)")
    p.set_defaults(func=_cmd_bench)

    p = sub.add_parser("warmup", help="compile every service's numba kernels ahead (once after installing: a "
                                      "fresh install's first start otherwise compiles for up to a minute)")
    p.add_argument("--json", action="store_true", help="print a JSON summary (seconds per part), no progress bar")
    p.set_defaults(func=_cmd_warmup)
    return parser


SERVICE_COMMANDS = ("camera", "tracker", "web")


def main(argv: list[str] | None = None) -> int:
    config.tune_malloc()  # before any thread starts
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=getattr(args, "log_level", "INFO"), stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except KeyboardInterrupt:
        return 130
    except ZError as exc:
        print(f"etam {args.command}: {config.zenoh_reason(exc)}", file=sys.stderr)
        return 2
    except (config.ConfigError, SourceError, FormatError, OSError, ValueError) as exc:
        print(f"etam {args.command}: {exc}", file=sys.stderr)
        return 2


def run() -> None:
    """Console-script entry. Service processes leave with os._exit once their session is closed:
    zenoh's threads can otherwise hold the interpreter at exit (DESIGN.md section 11)."""
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    logging.shutdown()
    os._exit(code)


if __name__ == "__main__":
    run()
