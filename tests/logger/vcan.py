"""Run a shell script with a real SocketCAN `vcan0` up: natively when this kernel has vcan, else inside a
virtme-ng VM (Debian's kernel under qemu, installed by .ci/vcan-setup) that sees the host's file system,
else skip the test with the reason.

The VM's root file system is the host's, read-only, except `workdir`, which the script writes into.
The script's output and exit code come back through files in `workdir` (virtme-ng's console fallback does
not pass them back reliably); its output is written as it runs, so a script stopped at its time limit still
tells how far it got. The VM runs in a process group of its own that is killed whatever happens: `vng` starts
qemu through two processes of its own, and killing `vng` alone would leave qemu running.
"""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
KERNEL_DIR = Path(os.environ.get("FUELID_VCAN_KERNEL_DIR", "/var/cache/fuelid-vcan"))
VENV_BIN = Path(sys.executable).parent
# From starting qemu to the script's first line under software emulation takes well under a minute; a VM that
# has not got there in this time is stuck in its boot and is started once more.
BOOT_S = 240.0
STOP_GRACE_S = 10  # a script at its time limit gets SIGTERM (the daemons close their files), SIGKILL this later
POWEROFF_S = 30.0  # the script has written its exit code: the VM is stopped if it has not powered off by then

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


def run_with_vcan(script: str, workdir: Path, timeout_s: float = 600) -> Result:
    """Run `script` (sh) in `workdir` with vcan0 up, the project venv first on PATH and `step TEXT` printing
    "== hh:mm:ss TEXT", for at most `timeout_s` [s] (the VM's boot not counted): then every process it started
    gets SIGTERM (its EXIT trap runs), SIGKILL `STOP_GRACE_S` later, and the result has returncode 124
    (coreutils timeout's) with the output so far."""
    mode = vcan_mode()
    workdir = workdir.resolve()
    body = workdir / "vcan-script.sh"
    # `step` marks how far the script got; at the time limit, TERM exits the shell so that its EXIT trap still runs
    prologue = 'step() { echo "== $(date +%T) $*"; }\ntrap \'exit 124\' TERM\n'
    body.write_text(f"set -u\nexport PATH={VENV_BIN}:$PATH\ncd {workdir}\n{prologue}{script}\n")
    limited = ["timeout", "-k", str(STOP_GRACE_S), str(timeout_s), "sh", str(body)]
    if mode == "native":
        done = subprocess.run(limited, capture_output=True, text=True)
        return Result(done.returncode, done.stdout + done.stderr, mode)

    pylib = workdir / "vm-pylib"
    pylib.mkdir(exist_ok=True)
    (pylib / "asammdf.py").write_text(_NO_ASAMMDF)
    # The VM cannot write the host's __pycache__ folders: compile the project's modules beforehand.
    subprocess.run([sys.executable, "-m", "compileall", "-q", "fuelid"], cwd=REPO, check=True)
    out, rc = workdir / "vm-output.txt", workdir / "vm-rc"
    wrapper = workdir / "vm-wrapper.sh"
    wrapper.write_text(
        f"export PYTHONPATH={pylib}\n"
        f"{{ modprobe vcan && ip link add vcan0 type vcan && ip link set vcan0 up; }} > {out} 2>&1 || {{ echo 98 > {rc}; exit; }}\n"
        f"{' '.join(limited)} >> {out} 2>&1\necho $? > {rc}\n"
    )
    cmd = [str(VENV_BIN / "vng"), "--run", str(KERNEL_DIR / "vmlinuz"), "--cpus", "2", "--memory", "2G",
           "--rwdir", str(workdir), "--exec", f"sh {wrapper}"]
    if not os.environ.get("FUELID_VCAN_KVM"):  # /dev/kvm may exist yet fail (nested): opt in to KVM
        cmd.insert(3, "--disable-kvm")
    env = {**os.environ, "PATH": f"{VENV_BIN}:{os.environ.get('PATH', '')}"}
    console = workdir / "vm-console.txt"
    for _ in range(2):
        out.unlink(missing_ok=True)
        rc.unlink(missing_ok=True)
        booted = _run_vm(cmd, env, console, started=out, finished=rc, limit_s=BOOT_S + timeout_s + 2 * STOP_GRACE_S)
        if booted:
            break
    if not rc.exists():
        where = "did not boot (twice)" if not booted else "did not finish the script"
        raise RuntimeError(f"the VM {where}; its console:\n{console.read_text()[-3000:]}\n"
                           f"the script's output:\n{out.read_text()[-3000:] if out.exists() else ''}")
    return Result(int(rc.read_text().strip() or 99), out.read_text(), mode)


def _run_vm(cmd: list[str], env: dict, console: Path, started: Path, finished: Path, limit_s: float) -> bool:
    """Run the VM until it powers off, for at most `limit_s` [s] and `POWEROFF_S` after `finished` appears;
    False when it did not reach the script (`started` absent) within `BOOT_S`. The VM's process group is
    killed on the way out in every case."""
    t0 = time.monotonic()
    done_at = None
    with console.open("w") as log:
        vm = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
                              start_new_session=True)
        try:
            while vm.poll() is None:
                elapsed = time.monotonic() - t0
                if done_at is None and finished.exists():
                    done_at = elapsed
                if (elapsed > limit_s or (elapsed > BOOT_S and not started.exists())
                        or (done_at is not None and elapsed > done_at + POWEROFF_S)):
                    break
                time.sleep(0.5)
            return started.exists()
        finally:
            try:
                os.killpg(vm.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            vm.wait()
