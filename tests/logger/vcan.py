"""Run a shell script with a real SocketCAN `vcan0` up: natively when this kernel has vcan, else inside a
virtme-ng VM (Debian's kernel under qemu, installed by .ci/vcan-setup) that sees the host's file system,
else skip the test with the reason.

The VM's root file system is the host's, read-only, except `workdir`, which the script writes into.
The script's output and exit code come back through files in `workdir` (virtme-ng's console fallback does
not pass them back reliably).
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
KERNEL_DIR = Path(os.environ.get("FUELID_VCAN_KERNEL_DIR", "/var/cache/fuelid-vcan"))
VENV_BIN = Path(sys.executable).parent

# Under software emulation importing asammdf (pandas, numpy) takes ~50 s, and nothing here reads MF4:
# python-can imports it optionally, so a module that refuses to import makes it skip MF4 support.
_NO_ASAMMDF = 'raise ImportError("asammdf is not loaded in the vcan VM")\n'


@dataclass
class Result:
    returncode: int
    output: str
    where: str  # "native" or "vm"


def _native_vcan() -> bool:
    if Path("/sys/class/net/vcan0").exists():
        return subprocess.run(["ip", "link", "set", "vcan0", "up"], capture_output=True).returncode == 0
    if not shutil.which("ip"):
        return False
    add = subprocess.run(["ip", "link", "add", "vcan0", "type", "vcan"], capture_output=True)
    return add.returncode == 0 and subprocess.run(["ip", "link", "set", "vcan0", "up"], capture_output=True).returncode == 0


def _vm_missing() -> str | None:
    """Why the VM cannot run here, or None."""
    kernel = KERNEL_DIR / "vmlinuz"
    version = (KERNEL_DIR / "version").read_text().strip() if (KERNEL_DIR / "version").exists() else ""
    checks = [
        (kernel.exists(), f"no kernel at {kernel}"),
        (bool(version) and Path(f"/lib/modules/{version}/kernel").is_dir(), f"no modules at /lib/modules/{version}"),
        ((VENV_BIN / "vng").exists(), "virtme-ng is not installed in the venv"),
        (shutil.which("qemu-system-x86_64") is not None, "qemu-system-x86_64 is not installed"),
        (shutil.which("busybox") is not None, "busybox is not installed"),
    ]
    missing = [why for ok, why in checks if not ok]
    return None if not missing else "; ".join(missing) + " (run .ci/vcan-setup as root)"


def vcan_mode() -> str:
    """"native" or "vm"; skips the calling test when neither works."""
    if _native_vcan():
        return "native"
    why = _vm_missing()
    if why:
        pytest.skip(f"no vcan: this kernel has no vcan module (or no root to add vcan0), and no VM: {why}")
    return "vm"


def run_with_vcan(script: str, workdir: Path, timeout_s: float = 900) -> Result:
    """Run `script` (sh) in `workdir` with vcan0 up and the project venv first on PATH."""
    mode = vcan_mode()
    workdir = workdir.resolve()
    body = workdir / "vcan-script.sh"
    body.write_text(f"set -u\nexport PATH={VENV_BIN}:$PATH\ncd {workdir}\n{script}\n")
    if mode == "native":
        done = subprocess.run(["sh", str(body)], capture_output=True, text=True, timeout=timeout_s)
        return Result(done.returncode, done.stdout + done.stderr, mode)

    pylib = workdir / "vm-pylib"
    pylib.mkdir(exist_ok=True)
    (pylib / "asammdf.py").write_text(_NO_ASAMMDF)
    # The VM cannot write the host's __pycache__ folders: compile the project's modules beforehand.
    subprocess.run([sys.executable, "-m", "compileall", "-q", "fuelid"], cwd=REPO, check=True)
    out, rc = workdir / "vm-output.txt", workdir / "vm-rc"
    rc.unlink(missing_ok=True)
    wrapper = workdir / "vm-wrapper.sh"
    wrapper.write_text(
        f"export PYTHONPATH={pylib}\n"
        f"{{ modprobe vcan && ip link add vcan0 type vcan && ip link set vcan0 up; }} > {out} 2>&1 || {{ echo 98 > {rc}; exit; }}\n"
        f"sh {body} >> {out} 2>&1\necho $? > {rc}\n"
    )
    cmd = [str(VENV_BIN / "vng"), "--run", str(KERNEL_DIR / "vmlinuz"), "--cpus", "2", "--memory", "2G",
           "--rwdir", str(workdir), "--exec", f"sh {wrapper}"]
    if not os.environ.get("FUELID_VCAN_KVM"):  # /dev/kvm may exist yet fail (nested): opt in to KVM
        cmd.insert(3, "--disable-kvm")
    env = {**os.environ, "PATH": f"{VENV_BIN}:{os.environ.get('PATH', '')}"}
    vng = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, env=env, stdin=subprocess.DEVNULL)
    if not rc.exists():
        raise RuntimeError(f"the VM did not run the script (vng exit {vng.returncode}):\n{vng.stdout[-3000:]}\n{vng.stderr[-3000:]}")
    return Result(int(rc.read_text().strip() or 99), out.read_text(), mode)
