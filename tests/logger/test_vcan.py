"""The daemon and replay through real SocketCAN: `fuelid log` on vcan0, `fuelid replay` onto it.

All checks but the last share one session on vcan0 (one VM boot where the kernel has no vcan, about 2 min under
software emulation): replay a log twice with the interface taken down and up in between, a flow-meter capture
on a pseudo-terminal, SIGTERM; then a daemon killed with SIGKILL mid-replay and the next start recovering its
file. The last, `fuelid log --identify` converging on a sped-up replay of a simulated trip, has its own.
"""
import json
import os
import subprocess
import sys

import pytest

import can
import numpy as np

from fuelid.cli import main
from fuelid.logger.j1939 import parse_id
from fuelid.logger.mcap_log import read_messages
from fuelid.logger.readers import read_frames
from tests.conftest import REPO
from tests.logger import traffic
from tests.logger.vcan import run_with_vcan

pytestmark = pytest.mark.vcan

DURATION_S = 6.0

SCRIPT = r"""
wait_for() {  # FILE PATTERN SECONDS
    i=0
    until grep -q "$2" "$1" 2>/dev/null; do
        i=$((i + 1)); [ $i -gt $(($3 * 5)) ] && { echo "TIMEOUT: no '$2' in $1 after $3 s"; cat "$1"; return 1; }
        sleep 0.2
    done
}
set -e
# The daemons write to the VM's own file system (/tmp: an overlay in memory), like the in-cab box to its
# local disk, not to the folder shared with the host (9p); the results are copied back at the end. On a
# failure the trap also kills what is left running, so the VM does not wait for it.
OUT=$(mktemp -d)
mkdir $OUT/run1 $OUT/run2
ln -s $OUT/run1 run1; ln -s $OUT/run2 run2
trap 'rc=$?; set +e; kill -KILL $(jobs -p) 2>/dev/null; rm run1 run2; cp -a $OUT/run1 $OUT/run2 .; exit $rc' EXIT
# Start-up takes ~20 s per Python process under emulation: start what can run side by side together.
# run1: flow meter on a pty; replay, interface down and up, replay again; SIGTERM.
# run2: a second daemon on the same bus, killed with SIGKILL during a third replay, then restarted.
step "start the flow meter and two daemons"
fuelid replay --flowmeter meter.flow --pty-link meter.pty --loop 2> flow-replay.err &
FLOW=$!
fuelid log --interface socketcan --channel vcan0 --serial meter.pty --output-dir run1 --truck vm-test > log1.err 2>&1 &
LOG1=$!
fuelid log --interface socketcan --channel vcan0 --output-dir run2 > log2.err 2>&1 &
LOG2=$!
wait_for run1/status.json '"state": "up"' 180
wait_for run2/status.json '"state": "up"' 180
wait_for run1/status.json '"state": "connected"' 60
step "replay 1"
fuelid replay drive.log --interface socketcan --channel vcan0 --json > replay1.json
sleep 2
step "vcan0 down and up"
ip link set vcan0 down
wait_for run1/status.json '"state": "down"' 30
sleep 2
ip link set vcan0 up
wait_for run1/status.json '"connects": 2' 60
wait_for run2/status.json '"connects": 2' 60
step "replay 2"
fuelid replay drive.log --interface socketcan --channel vcan0 --json > replay2.json
sleep 2
cat run1/status.json > status1.json  # cat reads the file it opened; cp fails when the daemon replaces it meanwhile
step "SIGTERM to daemon 1 and the flow meter"
kill -TERM $LOG1; wait $LOG1; echo $? > log1.rc
kill -TERM $FLOW; wait $FLOW || true
step "replay 3, SIGKILL to daemon 2"
fuelid replay drive.log drive.log --interface socketcan --channel vcan0 > replay3.txt &
REPLAY=$!
i=0  # wait until the third replay is under way
until [ "$(sed -n 's/^ "frames": \([0-9]*\),/\1/p' run2/status.json)" -ge @FRAMES@ ]; do
    i=$((i + 1)); [ $i -gt 600 ] && { echo "TIMEOUT: run2 never reached @FRAMES@ frames"; exit 1; }
    sleep 0.2
done
sleep 1
kill -KILL $LOG2; date +%s.%N > kill-time
ls run2 > run2-before.txt
rm run2/status.json
step "restart daemon 2"
fuelid log --interface socketcan --channel vcan0 --output-dir run2 > log3.err 2>&1 &
LOG3=$!
wait_for run2/status.json '"state": "up"' 180
kill -TERM $LOG3; wait $LOG3
step "end of replay 3"
wait $REPLAY
step done
"""


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    work = tmp_path_factory.mktemp("vcan")
    sent = traffic.write_candump(work / "drive.log", DURATION_S)
    traffic.write_capture(work / "meter.flow", DURATION_S)
    result = run_with_vcan(SCRIPT.replace("@FRAMES@", str(2 * len(sent) + 300)), work, timeout_s=600)
    if result.returncode != 0:
        logs = "\n".join(f"--- {p.name}\n{p.read_text()[-2000:]}" for p in sorted(work.glob("*.err")))
        pytest.fail(f"vcan session failed ({result.where}, exit {result.returncode}):\n{result.output[-4000:]}\n{logs}")
    return work, sent


def _messages(folder, topics=None):
    return [m for f in sorted(folder.glob("*.mcap")) for m in read_messages(f, topics)]


def test_every_replayed_frame_is_logged(session):
    work, sent = session
    replays = [json.loads((work / f"replay{i}.json").read_text()) for i in (1, 2)]
    assert [r["frames"] for r in replays] == [len(sent), len(sent)]
    raw = [rec for _, _, rec in _messages(work / "run1", "/can/raw")]
    assert len(raw) == 2 * len(sent)
    expected = [(m.arbitration_id, m.data.hex()) for m in sent] * 2
    assert [(r["id"], r["data"]) for r in raw] == expected
    assert all(r["channel"] == "vcan0" for r in raw)


def test_decoded_values_equal_convert(session, tmp_path):
    work, _ = session
    converted = tmp_path / "converted.mcap"
    subprocess.run([sys.executable, "-m", "fuelid.cli", "convert", str(work / "drive.log"), "-o", str(converted)],
                   check=True, capture_output=True)

    def by_topic(messages):
        out = {}
        for topic, _, rec in messages:
            if topic.startswith("/j1939/"):
                rec.pop("t")  # receive time: the replay's, not the recording's
                out.setdefault(topic, []).append(rec)
        return out

    want = by_topic(read_messages(converted))
    got = by_topic(_messages(work / "run1"))
    assert set(got) == set(want)
    for topic, records in want.items():
        assert got[topic] == records * 2, topic


def test_sigterm_closes_files_cleanly(session):
    work, _ = session
    assert (work / "log1.rc").read_text().strip() == "0"
    assert not list((work / "run1").glob("*.part"))
    status = json.loads((work / "run1" / "status.json").read_text())
    assert status["state"] == "stopped" and status["file"] is None


def test_bus_down_and_back(session):
    work, _ = session
    status = json.loads((work / "status1.json").read_text())
    assert status["bus"]["connects"] == 2 and status["bus"]["state"] == "up"
    assert status["faults"]["bus"] >= 1 and "down" in status["bus"]["last_error"]
    assert status["drops"] == 0


def test_flowmeter_through_pty(session):
    work, _ = session
    capture_volts = {float(line.split(",")[1]) for line in (work / "meter.flow").read_text().splitlines()[1:]
                     if "garbage" not in line}
    readings = [rec for _, _, rec in _messages(work / "run1", "/flowmeter")]
    ok = [r for r in readings if r["status"] == "ok"]
    assert len(ok) >= 20  # 10 readings/s for the whole session
    assert all(r["volts"] in capture_volts and r["flow_kg_h"] == pytest.approx(12.5 * r["volts"]) for r in ok)
    assert any(r["status"] == "invalid" and "garbage" in r["raw"] for r in readings)
    status = json.loads((work / "status1.json").read_text())
    assert status["serial"]["state"] == "connected" and 0 < status["serial"]["lines"] <= len(readings)


def test_sigkill_loses_at_most_a_second(session):
    work, sent = session
    before = (work / "run2-before.txt").read_text().split()
    assert any(name.endswith(".mcap.part") for name in before)  # the killed daemon's file
    assert not list((work / "run2").glob("*.part"))  # ... recovered by the next start
    kill_time = float((work / "kill-time").read_text())
    raw = [(t, rec) for _, t, rec in _messages(work / "run2", "/can/raw")]
    # the killed daemon saw both replays of run1 and part of the third
    assert len(raw) > 2 * len(sent)
    last_t = max(t for t, _ in raw) / 1e9
    # at most ~1 s lost (chunks are flushed every second), plus the emulated VM's sluggishness
    assert kill_time - last_t < 2.0
    sent_frames = {(m.arbitration_id, m.data.hex()) for m in sent}
    assert all((r["id"], r["data"]) in sent_frames for _, r in raw)


IDENTIFY_SPEED = 2  # the 400 s trip in 200 s; at 8x the emulated VM updated on only 287 of 1,269 bins (its
# replay stalls: a silence longer than max_gap_s / speed restarts the filters). Its stalls and late bursts made
# the from-scratch estimate diverge on about one CI run in two (last-third fit −2019 %, −208 %) until its start
# was fixed: tests/ident/test_live.py::test_from_scratch_converges_through_a_stalling_replay is that case on the host
IDENTIFY_ORDERS = "nb=2,2;nf=2,2;nk=3,0"  # a small output-error model: settles within minutes of the trip
# The engine's messages the estimator reads (EEC1, LFE1) and the transport protocol carrying EC1 (reference
# torque): the rest of the FMS traffic is left out to keep the emulated VM up with the sped-up replay.
IDENTIFY_PGNS = {0xF004, 0xFEF2, 0xEC00, 0xEB00}

IDENTIFY_SCRIPT = r"""
set -e
OUT=$(mktemp -d)
ln -s $OUT ident
trap 'rc=$?; set +e; kill -KILL $(jobs -p) 2>/dev/null; rm ident; cp -a $OUT ident; exit $rc' EXIT
# the estimator's compiled loop, built on the host for any x86-64 CPU (no JIT compile under emulation)
export NUMBA_CACHE_DIR=$PWD/numba-cache NUMBA_CPU_NAME=generic
step "start the daemon"
fuelid log --interface socketcan --channel vcan0 --output-dir ident --identify --orders "@ORDERS@" \
    --replay-speed @SPEED@ --snapshot-s 5 > log.err 2>&1 &
LOG=$!
i=0
until grep -q '"state": "up"' ident/status.json 2>/dev/null; do
    i=$((i + 1)); [ $i -gt 1500 ] && { echo "TIMEOUT: daemon not up"; exit 1; }
    sleep 0.2
done
step "replay the trip"
fuelid replay trip.log --interface socketcan --channel vcan0 --speed @SPEED@ --json > replay.json
sleep 3
cat ident/status.json > status.json  # cat reads the file it opened; cp fails when the daemon replaces it meanwhile
step "SIGTERM to the daemon"
kill -TERM $LOG; wait $LOG; echo $? > log.rc
step done
"""


@pytest.fixture(scope="module")
def identify_session(tmp_path_factory):
    work = tmp_path_factory.mktemp("vcan-identify")
    trip = work / "trip-full.log.gz"
    assert main(["simulate", "--truth", "diesel_p320", "--cycle", "urban", "--duration", "400", "--seed", "5",
                 "-o", str(trip)]) == 0
    sent = [m for m in read_frames(trip) if parse_id(m.arbitration_id).pgn in IDENTIFY_PGNS]
    with can.CanutilsLogWriter(str(work / "trip.log"), channel="can0") as w:
        for m in sent:
            w.on_message_received(m)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(work / "numba-cache"), "NUMBA_CPU_NAME": "generic"}
    build = ("import numpy as np; from fuelid.ident.polymodel import Structure; from fuelid.ident.rpem import RPEM; "
             "RPEM(Structure((2, 2), (2, 2), (3, 0)), 0.3).update(np.empty((0, 2)), np.empty(0))")
    subprocess.run([sys.executable, "-c", build], cwd=REPO, env=env, check=True)
    subprocess.run([sys.executable, "-m", "compileall", "-q", "fuelid/ident"], cwd=REPO, check=True)  # read-only in the VM
    script = IDENTIFY_SCRIPT.replace("@ORDERS@", IDENTIFY_ORDERS).replace("@SPEED@", str(IDENTIFY_SPEED))
    result = run_with_vcan(script, work, timeout_s=600)
    if result.returncode != 0:
        log = (work / "log.err").read_text()[-3000:] if (work / "log.err").exists() else ""
        pytest.fail(f"vcan identify session failed ({result.where}, exit {result.returncode}):\n"
                    f"{result.output[-4000:]}\n--- log.err\n{log}")
    return work, sent


def test_identify_on_replayed_trip_converges(identify_session):
    work, sent = identify_session
    assert json.loads((work / "replay.json").read_text())["frames"] == len(sent)
    assert (work / "log.rc").read_text().strip() == "0"
    status = json.loads((work / "status.json").read_text())
    assert status["identify"]["state"] == "running" and status["identify"]["errors"] == 0
    pred = [rec for _, _, rec in _messages(work / "ident", "/ident/prediction")]
    params = [rec for _, _, rec in _messages(work / "ident", "/ident/parameters")]
    assert len(pred) > 0.8 * 400 / 0.3 and len(_messages(work / "ident", "/ident/residual")) == len(pred)
    assert params and params[-1]["updates"] > 0.5 * len(pred)
    measured = np.array([np.nan if r["measured"] is None else r["measured"] for r in pred])
    simulated = np.array([np.nan if r["simulated"] is None else r["simulated"] for r in pred])
    third = len(pred) // 3

    def fit(a, b):
        ok = np.isfinite(a) & np.isfinite(b)
        return 100.0 * (1.0 - np.linalg.norm(a[ok] - b[ok]) / np.linalg.norm(a[ok] - a[ok].mean()))

    first, last = fit(measured[:third], simulated[:third]), fit(measured[-third:], simulated[-third:])
    assert last > 60.0 and last > first, (first, last)
    from fuelid.ident.modelfile import load_model

    assert load_model(work / "ident" / "model.json").structure.nf == (2, 2)
