"""deploy/: the units start real commands, the zenoh configs load, the router config serves a rig."""

from __future__ import annotations

import json
import logging
import re
import shlex
import subprocess
import time
from pathlib import Path

import pytest

from services import kernels
from services.cli import build_parser
from services.config import ZenohSettings
from tests.conftest import ROOT, etam_argv, free_port, spawn, wait_for

DEPLOY = ROOT / "deploy"


def _env() -> dict[str, str]:
    out = {}
    for line in (DEPLOY / "etam.env").read_text().splitlines():
        if line and not line.startswith("#"):
            k, _, v = line.partition("=")
            out[k] = v
    return out


@pytest.mark.parametrize("unit", sorted(p.name for p in (DEPLOY / "systemd").glob("*.service")))
def test_every_unit_runs_a_valid_etam_command(unit: str) -> None:
    text = (DEPLOY / "systemd" / unit).read_text()
    exec_start = re.search(r"^ExecStart=(.+)$", text, re.M).group(1)
    env = _env()
    argv = shlex.split(re.sub(r"\$\{(\w+)\}", lambda m: env[m.group(1)], exec_start))
    assert argv[0] == "/opt/etam/venv/bin/etam"
    args = build_parser().parse_args(argv[1:])  # exits (fails the test) on a wrong flag
    assert args.command == unit.removeprefix("etam-").removesuffix(".service")
    assert re.search(rf"Wants=.*{unit}", (DEPLOY / "systemd" / "etam.target").read_text())


def test_install_script_is_valid_bash() -> None:
    subprocess.run(["bash", "-n", str(DEPLOY / "install.sh")], check=True)


@pytest.mark.parametrize("name", ["router.json5", "ground-station.json5"])
def test_zenoh_configs_load(name: str) -> None:
    conf = ZenohSettings(config_file=str(DEPLOY / "zenoh" / name)).zenoh_config()
    assert "false" in conf.get_json("scouting/multicast/enabled")


def test_router_config_serves_a_rig(tmp_path: Path, rig: str) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = tmp_path / "router.json5"
    config.write_text((DEPLOY / "zenoh" / "router.json5").read_text().replace("tcp/0.0.0.0:7447", endpoint))
    with spawn("router", "--zenoh-config", str(config)), spawn("camera", "--connect", endpoint, "--rig", rig):
        def heard() -> bool:
            out = subprocess.run(etam_argv("echo", f"etam/{rig}/camera/cam0/info", "--count", "1", "--timeout", "5",
                                           "--connect", endpoint), cwd=ROOT, capture_output=True, text=True, timeout=30)
            return out.returncode == 0 and "CameraInfo" in out.stdout
        wait_for(heard, 30, "CameraInfo through the deployed router config", period_s=0.5)


@pytest.mark.parametrize("command", ["up", "router", "camera", "tracker", "web", "ls", "echo", "hz", "sim", "info",
                                     "convert", "record", "replay", "bench", "track", "eval", "warmup"])
def test_every_command_has_help(command: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        build_parser().parse_args([command, "--help"])
    assert exit_info.value.code == 0 and f"usage: etam {command}" in capsys.readouterr().out


def test_udev_rule_covers_every_camera_the_driver_opens() -> None:
    from fnmatch import fnmatch

    from services.camera.usb import protocol as pr

    rule = (DEPLOY / "udev" / "65-etam-inivation.rules").read_text()
    line = next(x for x in rule.splitlines() if x.startswith("SUBSYSTEM"))
    vendor = re.search(r'ATTR\{idVendor\}=="(\w+)"', line).group(1)
    product = re.search(r'ATTR\{idProduct\}=="([^"]+)"', line).group(1)
    assert int(vendor, 16) == pr.VID
    assert all(fnmatch(f"{pid:04x}", product) for pid in pr.PIDS)
    assert 'GROUP="video"' in line and "65-etam-inivation.rules" in (DEPLOY / "install.sh").read_text()


def test_warmup_loads_every_part_and_reports_each_as_json() -> None:
    run = subprocess.run(etam_argv("warmup", "--json"), cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    report = json.loads(run.stdout)
    assert list(report["parts"]) == list(kernels.PARTS) and all(s >= 0 for s in report["parts"].values())
    assert report["seconds"] == pytest.approx(sum(report["parts"].values()), abs=0.05)


def test_a_load_that_compiles_is_told_at_its_start_and_end_and_a_quick_one_is_not(
        caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    with caplog.at_level(logging.INFO, logger="services.kernels"):
        kernels.load("the quick part", lambda: None)  # well under the 2 s of `SLOW_S`
        monkeypatch.setattr(kernels, "SLOW_S", 0.05)
        kernels.load("the slow part", lambda: time.sleep(0.3))
    told = [r.getMessage() for r in caplog.records]
    assert not any("quick" in m for m in told)
    assert [m.split(":")[0] for m in told] == ["compiling the slow part's kernels",
                                               "the slow part's kernels ready in 0 s"]
