"""Which of a truck's files a refit uses: its newest recorded hours, never an empty selection."""
from fuelid.fleet.refits import newest_files

H_NS = 3600 * 10**9


def files(*hours):
    """Back-to-back files of the given lengths [h], oldest first, plus an empty log (no messages, no times)."""
    out, t = [], 0
    for k, h in enumerate(hours):
        out.append({"sha256": f"{k:064x}", "start_ns": t, "end_ns": t + int(h * H_NS)})
        t += int(h * H_NS)
    return out + [{"sha256": "e" * 64, "start_ns": None, "end_ns": None}]


def test_newest_hours_in_time_order():
    fs = files(10, 8, 6, 4)
    assert [f["sha256"] for f in newest_files(fs, 24 * 3600)] == [fs[1]["sha256"], fs[2]["sha256"], fs[3]["sha256"]]
    assert newest_files(fs, 100 * 3600) == fs[:4]  # the empty log holds no data to fit


def test_the_newest_file_is_taken_even_when_longer_than_the_window():
    fs = files(1, 30)
    assert newest_files(fs, 24 * 3600) == [fs[1]]
    assert newest_files(files(), 3600) == []
