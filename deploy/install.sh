#!/usr/bin/env bash
# Install ETAM on an onboard computer as systemd services (run as root from a checkout):
#   sudo deploy/install.sh            install, enable and start
#   sudo deploy/install.sh --no-start install and enable only
# Creates user `etam`, a virtualenv in /opt/etam/venv (its kernels compiled: `etam warmup`),
# /etc/etam/{etam.env,router.json5} (kept if they exist), the units etam-router, etam-camera, etam-tracker,
# etam-web, etam.target, and the udev rule for iniVation USB cameras (replug a camera plugged in before).
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
src="$(dirname "$here")"
start=1
[[ "${1:-}" == "--no-start" ]] && start=0
[[ $EUID -eq 0 ]] || { echo "install.sh: run as root (sudo)" >&2; exit 1; }
command -v python3 >/dev/null || { echo "install.sh: python3 (>= 3.11) is required" >&2; exit 1; }
python3 -c 'import sys; sys.exit(sys.version_info < (3, 11))' || { echo "install.sh: python3 >= 3.11 is required" >&2; exit 1; }

id etam >/dev/null 2>&1 || useradd --system --home-dir /opt/etam --shell /usr/sbin/nologin etam
# USB cameras: the etam user reads them through the udev rule's group (video)
getent group video >/dev/null || groupadd --system video
usermod -aG video etam
install -m 0644 "$here/udev/65-etam-inivation.rules" /etc/udev/rules.d/65-etam-inivation.rules
if command -v udevadm >/dev/null; then udevadm control --reload-rules && udevadm trigger --subsystem-match=usb || true; fi

mkdir -p /opt/etam /etc/etam
python3 -m venv /opt/etam/venv
/opt/etam/venv/bin/pip install --quiet --upgrade pip
/opt/etam/venv/bin/pip install --quiet "$src"
# numba compiles the kernels on their first run: here, once, not on the first flight's first seconds
echo "install.sh: compiling ETAM's kernels (about a minute on 2 cores; longer on a small board)"
/opt/etam/venv/bin/etam warmup
[[ -f /etc/etam/etam.env ]] || install -m 0644 "$here/etam.env" /etc/etam/etam.env
[[ -f /etc/etam/router.json5 ]] || install -m 0644 "$here/zenoh/router.json5" /etc/etam/router.json5
install -m 0644 "$here"/systemd/*.service "$here"/systemd/etam.target /etc/systemd/system/
chown -R etam: /opt/etam

systemctl daemon-reload
systemctl enable etam.target etam-router.service etam-camera.service etam-tracker.service etam-web.service
if [[ $start -eq 1 ]]; then
  systemctl restart etam.target
  echo "ETAM is running: systemctl status 'etam-*'; dashboard on port ${ETAM_WEB_PORT:-8080}"
fi
