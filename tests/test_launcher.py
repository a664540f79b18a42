"""`etam up` end to end: steady flows with no loss, restarts of a killed service, no orphans."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import psutil
import pytest

from services.launcher import SILENT_S, STARTUP_S, Child

from tests.conftest import ROOT, client_session, etam_argv, free_port, wait_for


def _rig_processes(rig: str) -> list[psutil.Process]:
    """The service processes (not the launcher) of one rig."""
    out = []
    for proc in psutil.process_iter(["cmdline"]):
        cmd = proc.info["cmdline"] or []
        if rig in cmd and "services.cli" in cmd and cmd[cmd.index("services.cli") + 1] != "up":
            out.append(proc)
    return out


def _trackers(rig: str, other_than: int | None = None) -> list[psutil.Process]:
    # the command line read once by process_iter: asking again raises for a killed tracker not yet reaped
    return [p for p in _rig_processes(rig) if "tracker" in p.info["cmdline"] and p.pid != other_than]


def _up(rig: str, report: Path, duration: float, *extra: str, listen: str | None = None) -> subprocess.Popen:
    return subprocess.Popen(
        etam_argv("up", "--duration", str(duration), "--no-web", "--report", str(report), "--rig", rig,
                  "--listen", listen or f"tcp/127.0.0.1:{free_port()}", "--log-level", "WARNING", *extra),
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )


@pytest.mark.slow
def test_up_runs_steady_with_no_loss(tmp_path: Path, rig: str) -> None:
    report_path = tmp_path / "r.json"
    proc = _up(rig, report_path, 20)
    out, err = proc.communicate(timeout=90)
    assert proc.returncode == 0, err
    report = json.loads(report_path.read_text())
    keys = report["keys"]
    events, truth, tracks = (keys[f"etam/{rig}/{k}"] for k in
                             ("camera/cam0/events", "camera/cam0/truth/boxes", "tracker/objects/tracks"))
    assert events["events"] > 100_000 and events["type"] == "EventPacket"
    for entry, rate in ((events, 1000), (truth, 50), (tracks, 100)):
        assert 0.8 * rate < entry["msg_rate"] < 1.2 * rate
        assert entry["dropped"] == 0 and entry["subscriber_dropped"] == 0 and entry["subscriber_malformed"] == 0
    assert all(s["restarts"] == 0 for s in report["services"].values())
    assert set(report["services"]) == {"camera", "tracker"}
    assert not _rig_processes(rig), "processes left behind"


@pytest.mark.slow
def test_killed_tracker_is_restarted_within_five_seconds(tmp_path: Path, rig: str) -> None:
    report_path = tmp_path / "r.json"
    proc = _up(rig, report_path, 15)
    try:
        tracker = wait_for(lambda: _trackers(rig), 20, "the tracker")[0]
        time.sleep(2)
        tracker.kill()
        killed_at = time.monotonic()
        new = wait_for(lambda: _trackers(rig, other_than=tracker.pid), 10, "a new tracker process")
        restart_s = time.monotonic() - killed_at
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert restart_s < 5.0
    assert proc.returncode == 0, err
    assert "tracker exited" in err and "restarting" in err
    report = json.loads(report_path.read_text())
    assert report["services"]["tracker"]["restarts"] == 1
    assert report["services"]["tracker"]["exit_codes"] == [-signal.SIGKILL]
    assert report["services"]["camera"]["restarts"] == 0
    assert not psutil.pid_exists(new[0].pid) or new[0].status() == psutil.STATUS_ZOMBIE
    assert not _rig_processes(rig)


@pytest.mark.slow
def test_sigint_stops_the_rig_without_orphans(tmp_path: Path, rig: str) -> None:
    proc = _up(rig, tmp_path / "r.json", 60)
    wait_for(lambda: len(_rig_processes(rig)) == 2, 20, "both services")
    time.sleep(1)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    assert (tmp_path / "r.json").exists()
    assert not _rig_processes(rig)


@pytest.mark.slow
def test_launcher_killed_hard_leaves_no_orphans(tmp_path: Path, rig: str) -> None:
    proc = _up(rig, tmp_path / "r.json", 60)
    wait_for(lambda: len(_rig_processes(rig)) == 2, 20, "both services")
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=20)
    wait_for(lambda: not _rig_processes(rig), 10, "the services to follow their launcher")


@pytest.mark.slow
def test_hung_service_is_detected_by_its_silence_and_restarted(tmp_path: Path, rig: str) -> None:
    report_path, endpoint = tmp_path / "r.json", f"tcp/127.0.0.1:{free_port()}"
    proc = _up(rig, report_path, 90, listen=endpoint)
    try:
        tracker = wait_for(lambda: _trackers(rig), 20, "the tracker")[0]
        stats: list[bytes] = []
        with client_session(endpoint) as session:
            sub = session.declare_subscriber(f"etam/{rig}/tracker/*/stats", lambda s: stats.append(s))
            wait_for(lambda: stats, 60, "the tracker's first Stats")  # silence counts from then
            sub.undeclare()
        tracker.suspend()  # alive, liveliness token still held, but doing nothing: hung
        wait_for(lambda: _trackers(rig, other_than=tracker.pid), 25, "a replacement for the hung tracker")
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert "tracker sent no Stats" in err
    report = json.loads(report_path.read_text())
    assert report["services"]["tracker"]["restarts"] == 1


def test_the_watchdog_gives_a_starting_service_longer_than_a_running_one() -> None:
    """A service is hung when its Stats stop for SILENT_S; before its first Stats (imports, numba compiling,
    a loaded CPU) it has STARTUP_S."""
    child = Child("probe", ["sleep", "60"])
    child.start(0.0)
    try:
        now = time.monotonic()
        child.started = now - SILENT_S - 1  # starting, silent longer than a running service may be
        child.kill_if_silent(None)
        assert child.proc.poll() is None
        child.kill_if_silent(now - 600)  # the Stats of an earlier run of it do not count
        assert child.proc.poll() is None
        child.kill_if_silent(now - SILENT_S + 2)  # running, Stats recent
        assert child.proc.poll() is None
        child.kill_if_silent(now - SILENT_S - 0.5)  # running, Stats stopped
        assert child.proc.wait(5) is not None
        child.start(0.0)
        child.started = time.monotonic() - STARTUP_S - 1  # never sent Stats in STARTUP_S
        child.kill_if_silent(None)
        assert child.proc.wait(5) is not None
    finally:
        child.stop()


def test_a_service_that_cannot_start_stops_the_rig_with_its_reason(tmp_path: Path, rig: str) -> None:
    proc = subprocess.Popen(
        etam_argv("up", "--duration", "60", "--no-web", "--rig", rig, "--listen", f"tcp/127.0.0.1:{free_port()}"),
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "ETAM_ZENOH_CONFIG": str(tmp_path / "missing.json5")},
    )
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 2
    assert "missing.json5 does not exist" in err and "not restarting" in err and "Traceback" not in err
    assert not _rig_processes(rig)


@pytest.mark.slow
def test_tracking_resumes_after_the_camera_restarts(tmp_path: Path, rig: str) -> None:
    from services.messages import Tracks, decode

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = subprocess.Popen(etam_argv("up", "--duration", "25", "--no-web", "--rig", rig, "--listen", endpoint,
                                      "--log-level", "WARNING"), cwd=ROOT, stderr=subprocess.PIPE, text=True)
    stamps: list[int] = []
    try:
        camera = wait_for(lambda: [p for p in _rig_processes(rig) if "camera" in p.cmdline()], 20, "camera")[0]
        with client_session(endpoint) as session:
            sub = session.declare_subscriber(f"etam/{rig}/tracker/objects/tracks",
                                             lambda s: stamps.append(decode(s.payload.to_bytes(), Tracks).t))
            wait_for(lambda: len(stamps) > 200, 20, "tracks before the restart")
            camera.kill()
            wait_for(lambda: any(b < a for a, b in zip(stamps, stamps[1:], strict=False)), 15,
                     "tracks from the new camera")
            restart = next(i for i, (a, b) in enumerate(zip(stamps, stamps[1:], strict=False)) if b < a) + 1
            wait_for(lambda: len(stamps) > restart + 100, 15, "steady tracks after the restart")
            sub.undeclare()
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    after = stamps[restart:]
    assert after[0] < 1_000_000 and after == sorted(after)  # the new camera's clock, in order


def test_a_source_slower_than_real_time_lags_but_stays_alive(tmp_path: Path, rig: str) -> None:
    """sim:rotation renders at about a tenth of real time: the camera must take bounded steps (and
    say it lags), not one ever longer step that silences its Stats until the launcher kills it."""
    report_path = tmp_path / "r.json"
    proc = _up(rig, report_path, 14, "--source", "sim:rotation")
    _out, err = proc.communicate(timeout=90)
    assert proc.returncode == 0, err
    report = json.loads(report_path.read_text())
    assert report["services"]["camera"]["restarts"] == 0
    stats = report["keys"][f"etam/{rig}/camera/cam0/stats"]
    assert stats["messages"] >= 3 and stats["max_gap_s"] < SILENT_S / 2  # Stats kept flowing, once started
    assert report["keys"][f"etam/{rig}/camera/cam0/truth/pose"]["messages"] > 5
    assert "plays slower than real time" in err
    assert report["keys"][f"etam/{rig}/tracker/ego/pose"]["messages"] > 20  # the tracker's rotation estimates


def test_up_on_a_spinning_camera_closes_the_loop(monkeypatch) -> None:  # noqa: ANN001
    """`etam up --source sim:rotation`: the tracker estimates the rotation and the mapper draws the mosaic
    with those poses, not the simulator's truth."""
    import services.launcher
    from services import cli
    from services.launcher import _children

    started = []
    monkeypatch.setattr(services.launcher, "up", lambda opts: started.append(opts) or 0)
    for source in ("sim:rotation", "sim:6dof"):
        assert cli.main(["up", "--source", source, "--no-web"]) == 0
    spin, moving = ({c.name: c.argv for c in _children(opts)} for opts in started)
    assert spin["tracker"][-2:] == ["--ego", "rotation"] and "--ego" not in moving["tracker"]
    spin_args, moving_args = (cli.build_parser().parse_args(argv[argv.index("mapper"):])
                              for argv in (spin["mapper"], moving["mapper"]))
    assert spin_args.poses == "ego" and spin_args.build == "mosaic" and moving_args.poses == "truth"


def test_up_maps_a_recording_with_truth_poses_when_asked(monkeypatch, tmp_path) -> None:  # noqa: ANN001
    """`etam up --map` adds the mapper on the recording's truth poses; a source without poses is refused by name."""
    import services.launcher
    from services import cli
    from services.camera.offline import simulate
    from services.launcher import _children

    h5 = tmp_path / "moving.h5"
    simulate("6dof", h5, 0.05, progress=False)
    started = []
    monkeypatch.setattr(services.launcher, "up", lambda opts: started.append(opts) or 0)
    assert cli.main(["up", "--source", str(h5), "--no-web"]) == 0
    assert cli.main(["up", "--source", str(h5), "--no-web", "--map"]) == 0
    plain, mapped = ({c.name: c.argv for c in _children(opts)} for opts in started)
    assert "mapper" not in plain and mapped["mapper"][-2:] == ["--poses", "truth"]
    assert cli.main(["up", "--source", "sim:objects", "--no-web", "--map"]) == 2
    assert len(started) == 2


def test_up_on_a_rig_tracks_boxes_of_its_first_camera_only(monkeypatch) -> None:  # noqa: ANN001
    """Tracks carry no camera: a tracker following both cameras of a stereo rig would put the right camera's
    boxes on the left camera's key (and do twice the work). `etam up` on a rig gives the tracker --cam cam0."""
    import services.launcher
    from services import cli
    from services.launcher import _children

    started = []
    monkeypatch.setattr(services.launcher, "up", lambda opts: started.append(opts) or 0)
    for source in ("sim:stereo", "sim:objects"):
        assert cli.main(["up", "--source", source, "--no-web"]) == 0
    stereo, mono = ({c.name: c.argv for c in _children(opts)} for opts in started)
    assert stereo["tracker"][-2:] == ["--cam", "cam0"]
    assert "--cam" not in mono["tracker"]
    assert cli.build_parser().parse_args(["tracker", "--cam", "cam1"]).cam == "cam1"


def test_the_dashboard_runs_at_a_lower_priority_than_the_services() -> None:
    """On a drone's few cores the viewer must not delay tracking: `etam up` starts it niced."""
    from services.launcher import VIEWER_NICE, Child, UpOptions, _children

    children = {c.name: c for c in _children(UpOptions(rig="r"))}
    assert children["web"].nice == VIEWER_NICE > 0 and children["tracker"].nice == children["camera"].nice == 0
    child = Child("sleeper", ["sleep", "30"], nice=VIEWER_NICE)
    child.start(time.monotonic())
    expected = min(os.getpriority(os.PRIO_PROCESS, 0) + VIEWER_NICE, 19)
    try:
        assert os.getpriority(os.PRIO_PROCESS, child.proc.pid) == expected
    finally:
        child.proc.kill()
        child.proc.wait()
