#!/usr/bin/env bash
# Install Kestrel VIO as a systemd service on the companion computer (Raspberry Pi OS, Ubuntu on Jetson,
# any Debian-like system with systemd). Idempotent: run it again after `git pull` to upgrade; it never
# overwrites an existing /etc/kestrel-vio/config.toml.
#
#   sudo systemd/install.sh [--dry-run] [--enable] [--no-venv] [--prefix /opt/kestrel-vio]
#
#   --dry-run   print every command instead of running it (no root needed)
#   --enable    also `systemctl enable --now kestrel-vio`
#   --no-venv   skip creating/upgrading the virtual environment (e.g. offline, already installed)
#   --prefix D  install under D instead of /opt/kestrel-vio
set -euo pipefail

SERVICE_USER=kestrel
PREFIX=/opt/kestrel-vio
ETC=/etc/kestrel-vio
UNIT_DIR=/etc/systemd/system
UDEV_DIR=/etc/udev/rules.d
DRY_RUN=0
ENABLE=0
VENV=1
SRC="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"

while [[ $# -gt 0 ]]; do
    case "$1" in
        --dry-run) DRY_RUN=1 ;;
        --enable) ENABLE=1 ;;
        --no-venv) VENV=0 ;;
        --prefix)
            if [[ $# -lt 2 || -z "$2" || "$2" == -* ]]; then
                echo "install.sh: --prefix needs a folder (e.g. --prefix /opt/kestrel-vio)" >&2; exit 2
            fi
            PREFIX="$2"; shift ;;
        -h|--help) sed -n '2,11p' "$0"; exit 0 ;;
        *) echo "install.sh: unknown option '$1' (try --help)" >&2; exit 2 ;;
    esac
    shift
done

run() {  # print (quoted as a shell reads it back), and execute unless --dry-run
    echo "+$(printf ' %q' "$@")"
    if [[ $DRY_RUN -eq 0 ]]; then "$@"; fi
}

if [[ $DRY_RUN -eq 0 && $EUID -ne 0 ]]; then
    echo "install.sh: run as root (sudo $0 $*), or with --dry-run to see what it would do" >&2
    exit 1
fi
if [[ ! -f "$SRC/pyproject.toml" || ! -f "$SRC/systemd/kestrel-vio.service" ]]; then
    echo "install.sh: $SRC does not look like the kestrel-vio source tree" >&2
    exit 1
fi

# 1. Groups and the service user (no login shell, no home directory outside /var/lib/kestrel-vio).
for group in dialout plugdev; do
    getent group "$group" >/dev/null || run groupadd --system "$group"
done
if ! id -u "$SERVICE_USER" >/dev/null 2>&1; then
    run useradd --system --user-group --home-dir /var/lib/kestrel-vio --no-create-home \
        --shell /usr/sbin/nologin --comment "Kestrel VIO service" "$SERVICE_USER"
fi
# Membership also lets `sudo -u kestrel vio ...` reach the devices when debugging from a shell.
run usermod --append --groups dialout,plugdev "$SERVICE_USER"

# 2. Python environment under $PREFIX (system Python 3.10+; the package pulls numpy, gtsam...; the [oak] and
#    [serial] extras add depthai and pyserial, which the onboard service needs).
if [[ $VENV -eq 1 ]]; then
    if [[ ! -x "$PREFIX/venv/bin/python" ]]; then
        run mkdir -p "$PREFIX"
        run python3 -m venv "$PREFIX/venv"
    fi
    run "$PREFIX/venv/bin/pip" install --upgrade --quiet pip
    run "$PREFIX/venv/bin/pip" install --upgrade --quiet "$SRC[oak,serial]"
fi
run install -d -m 0755 "$PREFIX/docs"
run install -m 0644 "$SRC"/docs/*.md "$PREFIX/docs/"  # the unit's Documentation= points here
if [[ "$PREFIX" != /opt/kestrel-vio ]]; then
    # a drop-in's ExecStart= adds a second one (refused for Type=notify) unless an empty line clears the first
    printf '%s\n' "note: the unit file runs /opt/kestrel-vio/venv/bin/vio; with --prefix $PREFIX put these two lines" \
        "under [Service] in 'sudo systemctl edit kestrel-vio' (the empty ExecStart= clears the unit's own):" \
        "ExecStart=" "ExecStart=$PREFIX/venv/bin/vio run --config $ETC/config.toml" >&2
fi

# 3. Configuration: the example is always refreshed beside it, the live file is never overwritten.
run install -d -m 0755 "$ETC"
run install -m 0644 "$SRC/systemd/config.toml" "$ETC/config.toml.example"
if [[ -e "$ETC/config.toml" ]]; then
    echo "keeping existing $ETC/config.toml (compare with $ETC/config.toml.example after upgrades)"
else
    run install -m 0644 "$SRC/systemd/config.toml" "$ETC/config.toml"
fi

# 4. udev rule for OAK cameras, then the unit.
run install -m 0644 "$SRC/systemd/80-kestrel-oak.rules" "$UDEV_DIR/80-kestrel-oak.rules"
if command -v udevadm >/dev/null 2>&1; then
    run udevadm control --reload-rules
    run udevadm trigger --subsystem-match=usb --attr-match=idVendor=03e7
fi
run install -m 0644 "$SRC/systemd/kestrel-vio.service" "$UNIT_DIR/kestrel-vio.service"
run systemctl daemon-reload

# 5. Check the configuration with the installed program (exit code 3 would stop the service anyway).
if [[ $VENV -eq 1 || -x "$PREFIX/venv/bin/vio" ]]; then
    run "$PREFIX/venv/bin/vio" config check "$ETC/config.toml"
fi

if [[ $ENABLE -eq 1 ]]; then
    run systemctl enable --now kestrel-vio
    echo "started: follow with 'journalctl -u kestrel-vio -f'; health with '$PREFIX/venv/bin/vio status'"
else
    echo "installed. Edit $ETC/config.toml, then: sudo systemctl enable --now kestrel-vio"
fi
