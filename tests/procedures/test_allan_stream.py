"""Long recordings in bounded memory (issue 41, issue 36 item 5): the chunked Allan deviation against
allantools in memory, the streamed path forced by a small memory budget against the in-memory one,
and hostile text (1e308, nan, more rows than the budget holds) refused in one line naming the row."""
from __future__ import annotations

import gzip
import json

import numpy as np
import pytest
from imubench import memory
from imubench.analysis.allan import oadev_chunked, oadev_in_memory
from imubench.cli import main as imubench
from imubench.procedures.allan import analyse_recording
from imubench.recordings import RecordingError, read

FS_HZ = 200.0


def test_chunked_oadev_is_allantools_to_rounding():
    """Blocks far smaller than the data (carries across 40 blocks), float32 input and a unit factor."""
    rng = np.random.default_rng(3)
    y = (1.0 + rng.normal(0, 1e-3, 40_001) + np.cumsum(rng.normal(0, 1e-5, 40_001))).astype(np.float32)
    t1, d1, n1 = oadev_in_memory(y, FS_HZ, 9.80665)
    t2, d2, n2 = oadev_chunked(y, FS_HZ, 9.80665, block=1000)
    assert np.array_equal(t1, t2) and np.array_equal(n1, n2) and len(t1) == 15
    np.testing.assert_allclose(d2, d1, rtol=1e-12, atol=0)


def _counts_csv(path, n: int, seed: int = 5) -> None:
    """A still IMU's raw counts (integers: float32 holds them exactly) with a time column in s."""
    rng = np.random.default_rng(seed)
    acc = np.round(rng.normal(0, 40, (n, 3)) + [0, 0, 16384] + np.cumsum(rng.normal(0, 0.3, (n, 3)), axis=0))
    gyr = np.round(rng.normal(0, 8, (n, 3)) + np.cumsum(rng.normal(0, 0.05, (n, 3)), axis=0))
    with open(path, "w") as f:
        f.write("t_s,ax,ay,az,gx,gy,gz\n")
        np.savetxt(f, np.column_stack([np.arange(n) / FS_HZ, acc, gyr]), delimiter=",",
                   fmt=["%.3f"] + ["%d"] * 6)


def test_small_budget_streams_and_agrees_with_the_in_memory_path(tmp_path, monkeypatch):
    """A budget just above what the process itself takes forces float32 storage and the chunked sums:
    the read-offs and every point of the curve agree with the default path within 1e-9 (the plots,
    which only draw the curve, are left out for time)."""
    monkeypatch.setattr("imubench.procedures.allan.plot_allan", lambda *a, **k: None)
    f = tmp_path / "still.csv"
    n = 40_000
    _counts_csv(f, n)
    opts = dict(accel_unit="counts", gyro_unit="counts", accel_counts_per_g=16384.0, gyro_counts_per_dps=131.0)
    small = memory.BASE_BYTES + 2_000_000          # float64 storage needs 2.56 MB, float32 1.6 MB
    ref = read(f, **opts)
    low = read(f, memory_budget=small, **opts)
    assert ref.accel.dtype == np.float64 and low.accel.dtype == np.float32 and len(low) == n
    r1 = analyse_recording(ref, tmp_path / "ref", log=lambda s: None)
    r2 = analyse_recording(low, tmp_path / "low", log=lambda s: None, memory_budget=small)
    assert r1["method"] == "allantools.oadev in memory" and r2["method"].startswith("chunked sums")
    assert "float32" in r2["storage"]
    for kind in ("accel", "gyro"):
        for ax in "xyz":
            a, b = r1[kind][ax], r2[kind][ax]
            np.testing.assert_allclose(b["adev"], a["adev"], rtol=1e-9, atol=0)
            for key in ("N", "B", "K"):
                assert (a[key] is None) == (b[key] is None), (kind, ax, key)
                if a[key] is not None:
                    assert b[key] == pytest.approx(a[key], rel=1e-9, abs=0), (kind, ax, key)
    saved = json.loads((tmp_path / "low" / "allan.json").read_text())
    assert saved["method"].startswith("chunked sums") and saved["samples"] == n


def test_sample_limit_is_checked_before_reading(tmp_path):
    """More rows than the budget holds, in a small .csv.gz: refused from the count of its lines (which
    stops past the limit), naming the limit and the option that raises it; the default holds 24 h."""
    f = tmp_path / "many.csv.gz"
    with gzip.open(f, "wt") as g:
        g.write("t_s,ax,ay,az,gx,gy,gz\n")
        g.write("".join(f"{i / 200:.3f},0,0,1,0,0,0\n" for i in range(300_000)))
    budget = memory.BASE_BYTES + 4_000_000                 # 100,000 samples of float32 + time + work
    with pytest.raises(RecordingError, match=r"more than 100,000 samples.*--memory-budget"):
        read(f, accel_unit="g", gyro_unit="dps", memory_budget=budget)
    assert memory.sample_limit() > 24 * 3600 * 200


def test_calibrate_limit_counts_what_its_analysis_takes(tmp_path, capsys):
    """calibrate --from takes ~200 B a sample after the read: its limit under a 200 MB budget is
    250,000 samples, said before anything is read into memory; allan --from's is 1.25 M."""
    f = tmp_path / "many.csv.gz"
    with gzip.open(f, "wt") as g:
        g.write("".join(f"{i / 200:.3f},0,0,1,0,0,0\n" for i in range(260_000)))
    assert imubench(["calibrate", "--from", str(f), "--accel-unit", "g", "--gyro-unit", "dps", "--memory-budget",
                     "200M", "--dir", str(tmp_path / "c")]) == 1
    err = capsys.readouterr().err
    assert "more than 250,000 samples" in err and "200 B a sample" in err and "--memory-budget" in err
    assert memory.sample_limit(200_000_000) == 1_250_000


@pytest.mark.parametrize("value, said", [("1e308", "1e+308, beyond any sensor's range"),
                                         ("nan", "not a finite number"), ("-inf", "not a finite number")])
def test_absurd_or_non_finite_value_names_its_line(tmp_path, capsys, value, said):
    f = tmp_path / "bad.csv"
    rows = [f"{i / 200:.3f},0.01,0.02,1.0,0.1,0.2,0.3" for i in range(50)]
    rows[40] = f"0.200,0.01,{value},1.0,0.1,0.2,0.3"
    f.write_text("t_s,ax,ay,az,gx,gy,gz\n" + "\n".join(rows) + "\n")
    assert imubench(["allan", "--from", str(f), "--accel-unit", "g", "--gyro-unit", "dps",
                     "--out", str(tmp_path / "o")]) != 0
    err = capsys.readouterr().err
    assert f"line 42, ay: {said}" in err and "internal error" not in err and "Traceback" not in err
    assert imubench(["calibrate", "--from", str(f), "--accel-unit", "g", "--gyro-unit", "dps",
                     "--dir", str(tmp_path / "c")]) != 0
    err = capsys.readouterr().err
    assert f"line 42, ay: {said}" in err and "internal error" not in err


def test_memory_budget_option_rejects_nonsense(tmp_path, capsys):
    f = tmp_path / "x.csv"
    f.write_text("t_s,ax,ay,az,gx,gy,gz\n")
    for bad in ("lots", "10M"):
        assert imubench(["allan", "--from", str(f), "--memory-budget", bad]) == 2
        err = capsys.readouterr().err
        assert "--memory-budget" in err and "Traceback" not in err


def test_a_constant_axis_is_said_not_an_internal_error(tmp_path, capsys):
    """A gyro column that never varies (stuck output, a constant written by a logger) has no Allan
    deviation: one line naming the sensor and the axis."""
    rng = np.random.default_rng(2)
    f = tmp_path / "stuck.csv"
    rows = [f"{i / 100:.2f},{rng.normal(0, 1e-3):.6f},{rng.normal(0, 1e-3):.6f},{1 + rng.normal(0, 1e-3):.6f},"
            f"0.1,0.2,0.3" for i in range(8000)]
    f.write_text("t_s,ax,ay,az,gx,gy,gz\n" + "\n".join(rows) + "\n")
    assert imubench(["allan", "--from", str(f), "--accel-unit", "g", "--gyro-unit", "dps",
                     "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert "the gyro's axis x: its samples do not vary" in err and "internal error" not in err


def _moving_counts_csv(path, seed: int = 8) -> None:
    """Raw counts (exact in float32) of 30 s still, a 4 s turn about the vertical that only the gyro sees,
    70 s still, a 3 s shove the accelerometer sees, 25 s still: three stretches, the middle one longest."""
    rng = np.random.default_rng(seed)
    parts = []
    for k, (still_s, move) in enumerate(((30, "turn"), (70, "shove"), (25, None))):
        n = int(still_s * FS_HZ)
        parts.append((rng.normal(0, 40, (n, 3)) + [0, 0, 16384], rng.normal(0, 8, (n, 3))))
        if move:
            m = int((4 if move == "turn" else 3) * FS_HZ)
            a, g = rng.normal(0, 40, (m, 3)) + [0, 0, 16384], rng.normal(0, 8, (m, 3))
            bump = np.sin(np.linspace(0, np.pi, m))
            if move == "turn":
                g[:, 2] += 131.0 * 180.0 * bump            # ~180 °/s at its peak, gravity unmoved
            else:
                a[:, 0] += 8000.0 * bump                   # ~0.5 g along x
            parts.append((a, g))
    acc, gyr = np.vstack([p[0] for p in parts]), np.vstack([p[1] for p in parts])
    with open(path, "w") as f:
        f.write("t_s,ax,ay,az,gx,gy,gz\n")
        np.savetxt(f, np.column_stack([np.arange(len(acc)) / FS_HZ, np.round(acc), np.round(gyr)]),
                   delimiter=",", fmt=["%.3f"] + ["%d"] * 6)


def test_small_budget_finds_the_same_still_stretch_a_block_at_a_time(tmp_path, monkeypatch):
    """A recording with a turn and a shove, read under the default budget (float64) and under one that
    forces float32 storage and the chunked Allan sums: allan --from finds its still stretch a block at a
    time on either storage (blocks of ~2000 rows: the runs and the gyro's cuts are carried across
    blocks; runs over 3000 samples have their drift from block sums), and it is the stretch of the
    in-memory search (still_stretch on float64 SI copies) exactly; the read-offs agree within 1e-9."""
    import imubench.calib.static as static
    import imubench.calib.still_blocks as still_blocks
    from imubench.procedures.allan import still_stretch
    monkeypatch.setattr("imubench.procedures.allan.plot_allan", lambda *a, **k: None)
    monkeypatch.setattr(static, "VAR_BLOCK_ROWS", 2000)
    monkeypatch.setattr(still_blocks, "EXACT_ROWS", 3000)
    f = tmp_path / "moving.csv"
    _moving_counts_csv(f)
    opts = dict(accel_unit="counts", gyro_unit="counts", accel_counts_per_g=16384.0, gyro_counts_per_dps=131.0)
    ref = read(f, **opts)
    small = memory.BASE_BYTES + 1_500_000      # float32 storage (1.1 MB), no float64 copy of an axis
    low = read(f, memory_budget=small, **opts)
    assert ref.accel.dtype == np.float64 and low.accel.dtype == np.float32
    in_memory = still_stretch(ref.accel * ref.accel_factor(), ref.gyro * ref.gyro_factor(), ref.fs_hz)
    r1 = analyse_recording(ref, tmp_path / "ref", log=lambda s: None)
    r2 = analyse_recording(low, tmp_path / "low", log=lambda s: None, memory_budget=small)
    assert r2["method"].startswith("chunked sums") and r1["method"] == "allantools.oadev in memory"
    assert r2["still"] == r1["still"] == in_memory
    assert in_memory["stretches"] == 3 and in_memory["start"] > 34 * FS_HZ and in_memory["duration_s"] > 60
    for kind in ("accel", "gyro"):
        for ax in "xyz":
            a, b = r1[kind][ax], r2[kind][ax]
            np.testing.assert_allclose(b["adev"], a["adev"], rtol=1e-9, atol=0)
            for key in ("N", "B", "K"):
                if a[key] is None:
                    assert b[key] is None
                else:
                    assert b[key] == pytest.approx(a[key], rel=1e-9, abs=0), (kind, ax, key)


def test_block_search_is_the_in_memory_one_on_float64_and_float32():
    """still_stretch_blocks against still_stretch on the SI arrays, for float64 storage and for float32
    storage scaled by a factor, with blocks far smaller than the recording: the same stretch."""
    import imubench.calib.static as static
    from imubench.procedures.allan import still_stretch, still_stretch_blocks
    rng = np.random.default_rng(4)
    g0 = 9.80665
    parts = [(rng.normal(0, 2e-3, (n, 3)) + [0, 0, g0], rng.normal(0, 1e-3, (n, 3))) for n in (9000, 14000, 5000)]
    shove = rng.normal(0, 2e-3, (500, 3)) + [0, 0, g0]
    shove[:, 1] += 3.0 * np.sin(np.linspace(0, np.pi, 500))
    acc = np.vstack([parts[0][0], shove, parts[1][0], parts[2][0]])
    turn = np.zeros((len(acc), 3))
    turn[9500 + 14000:9500 + 14000 + 400, 2] = 2.0          # a yaw between the second and third rest
    gyr = np.vstack([parts[0][1], rng.normal(0, 1e-3, (500, 3)), parts[1][1], parts[2][1]]) + turn
    old = static.VAR_BLOCK_ROWS
    try:
        static.VAR_BLOCK_ROWS = 3000
        for dtype, f in ((np.float64, 1.0), (np.float32, 1.0 / g0)):
            a, g = (acc * f).astype(dtype), gyr.astype(dtype)
            ref = still_stretch(a * (1 / f if f != 1.0 else 1.0), g * 1.0, FS_HZ)
            got = still_stretch_blocks(a, g, FS_HZ, 1 / f if f != 1.0 else 1.0, 1.0)
            assert got == ref, dtype
            assert ref["stretches"] == 3 and 9500 <= ref["start"] and ref["stop"] <= 23500, ref   # the second rest
    finally:
        static.VAR_BLOCK_ROWS = old


def _irregular(seed: int, n: int = 20_000):
    """Time stamps of a logging PC: 0.8 ms RMS jitter on 5 ms steps, a clock 3 % slow for the first half
    (the grid runs ahead of the samples there), 40 repeated stamps (half with repeated values too) and
    three gaps; float32 values."""
    rng = np.random.default_rng(seed)
    steps = np.full(n - 1, 0.005)
    steps[: n // 2] *= 1.03
    steps += rng.normal(0, 0.0008, n - 1).clip(-0.004, 0.004)
    steps[rng.choice(n - 1, 40, replace=False)] = 0.0
    steps[[3000, 9000, 15000]] = [0.3, 0.8, 0.05]
    t = np.concatenate([[10.0], 10.0 + np.cumsum(steps)])
    a, g = rng.normal(0, 1, (n, 3)), rng.normal(0, 1, (n, 3))
    rep = np.flatnonzero(steps == 0)[::2] + 1
    a[rep], g[rep] = a[rep - 1], g[rep - 1]
    return t, a.astype(np.float32), g.astype(np.float32)


def _timing_reference(t, a, g):
    """What check_timing does, on whole arrays: drop the repeated stamps, then each piece between the
    gaps onto a grid from its first stamp at the mean step (numpy.interp), in the values' type."""
    from imubench.recordings import check_timing
    *_, breaks, timing = check_timing(t, a, g, resample=False)
    keep = np.concatenate([[True], np.diff(t) != 0])
    t, a, g = t[keep], a[keep], g[keep]
    mean = timing["mean_dt_s"]
    cuts = [gp["index"] for gp in timing["gaps"]]
    ts, As, Gs = [], [], []
    for p0, p1 in zip([0] + cuts, cuts + [len(t)]):
        grid = t[p0] + np.arange(int(np.floor((t[p1 - 1] - t[p0]) / mean + 1e-9)) + 1) * mean
        ts.append(grid)
        As.append(np.column_stack([np.interp(grid, t[p0:p1], a[p0:p1, j]) for j in range(3)]).astype(a.dtype))
        Gs.append(np.column_stack([np.interp(grid, t[p0:p1], g[p0:p1, j]) for j in range(3)]).astype(g.dtype))
    return np.concatenate(ts), np.concatenate(As), np.concatenate(Gs)


@pytest.mark.parametrize("step", [257, 1 << 18])
def test_repeats_and_resampling_a_block_at_a_time_in_place(monkeypatch, step):
    """Dropping repeated stamps and resampling a jittery clock, a block of `step` rows at a time: written
    over a reader's own arrays (in place) or into new ones (the caller's arrays are left alone), both
    exactly the whole-array computation; the grid running ahead of the samples (the slow half) overwrites
    rows it still needs, which are kept aside."""
    import imubench.recordings as recordings
    monkeypatch.setattr(recordings, "STEP_ROWS", step)
    t, a, g = _irregular(1)
    want = _timing_reference(t.copy(), a.copy(), g.copy())
    mine = (t.copy(), a.copy(), g.copy())
    copied = recordings.check_timing(*mine)
    assert np.array_equal(mine[1], a) and np.array_equal(mine[0], t)          # the caller's arrays untouched
    own = (t.copy(), a.copy(), g.copy())
    inplace = recordings.check_timing(*own, in_place=True)
    assert np.shares_memory(inplace[1], own[1]) and np.shares_memory(inplace[0], own[0])
    for got in (copied, inplace):
        timing = got[5]
        assert timing["resampled"] and timing["duplicates"] == 40 and timing["duplicates_identical"] == 20
        assert len(timing["gaps"]) >= 3 and got[4] == copied[4] and timing["gaps"] == copied[5]["gaps"]
        for x, y in zip(got[:3], want):
            assert x.dtype == y.dtype and np.array_equal(x, y)


def test_resampling_in_place_holds_no_second_recording(monkeypatch):
    """200,000 jittery samples read by a reader (from_arrays copy=False): the timing check's peak beyond
    the recording is its one float64 working column and blocks, not a second recording (56 B a sample)."""
    import tracemalloc

    import imubench.recordings as recordings
    monkeypatch.setattr(recordings, "STEP_ROWS", 4096)
    monkeypatch.setattr(recordings, "BLOCK", 4096)
    rng = np.random.default_rng(2)
    n = 200_000
    t = np.cumsum(0.005 + rng.normal(0, 0.0008, n).clip(-0.004, 0.004))
    a, g = rng.normal(0, 1, (n, 3)).astype(np.float32), rng.normal(0, 1, (n, 3)).astype(np.float32)
    tracemalloc.start()
    rec = recordings.from_arrays(a, g, t_s=t, copy=False)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert rec.timing["resampled"] and np.shares_memory(rec.accel, a)
    assert peak < 12 * n, f"{peak / n:.1f} B a sample"


def test_a_ros1_bag_is_read_without_holding_its_message_index(tmp_path, monkeypatch):
    """rosbags' ROS 1 reader holds a Python tuple for every message of the bag (~170 B: 3 GB for a day at
    200 Hz) before a sample is read; imubench's counts them instead: the same samples as with rosbags'
    own reader (several chunks), and at least 100 B a message less at the peak."""
    import struct
    import tracemalloc

    import imubench.recordings.bags as bags
    from rosbags.rosbag1 import Reader, Writer     # a test dependency (pyproject's test extra)
    from rosbags.typesys import Stores, get_typestore
    n = 12_000
    rng = np.random.default_rng(6)
    acc, gyr = rng.normal(0, 0.01, (n, 3)) + [0, 0, 9.8], rng.normal(0, 1e-3, (n, 3))
    pack = struct.Struct("<IIII3s4d9d3d9d3d9d").pack          # sensor_msgs/Imu, ROS 1, frame_id "imu"
    p = tmp_path / "still.bag"
    with Writer(p) as w:
        c = w.add_connection("/imu0", "sensor_msgs/msg/Imu", typestore=get_typestore(Stores.ROS1_NOETIC))
        for i in range(n):
            ns = 1_700_000_000 * 10**9 + i * 5_000_000
            w.write(c, ns, pack(i, ns // 10**9, ns % 10**9, 3, b"imu", 0.0, 0.0, 0.0, 1.0, *(0.0,) * 9, *gyr[i],
                                *(0.0,) * 9, *acc[i], *(0.0,) * 9))
    read(p)                                                      # imports outside the measurement
    peaks = {}
    for name in ("imubench", "rosbags"):
        if name == "rosbags":
            monkeypatch.setattr(bags, "_ros1_reader", lambda: Reader)
        tracemalloc.start()
        rec = read(p)
        peaks[name] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert rec.fmt == "rosbag" and len(rec) == n and abs(rec.fs_hz - 200.0) < 1e-6
        np.testing.assert_array_equal(rec.accel, acc)
        np.testing.assert_array_equal(rec.gyro, gyr)
    assert peaks["rosbags"] - peaks["imubench"] > 100 * n, {k: v / n for k, v in peaks.items()}


def test_bag_messages_of_changing_layouts_are_decoded_in_order(tmp_path):
    """Messages are decoded a block of one layout at a time: a frame_id whose length changes every 300
    messages (three layouts) and stamps set apart from the receive times give every value back, in order."""
    import struct

    from rosbags.rosbag1 import Writer     # a test dependency (pyproject's test extra)
    from rosbags.typesys import Stores, get_typestore
    n = 2000
    rng = np.random.default_rng(9)
    acc, gyr = rng.normal(0, 0.01, (n, 3)) + [0, 0, 9.8], rng.normal(0, 1e-3, (n, 3))
    p = tmp_path / "frames.bag"
    with Writer(p) as w:
        c = w.add_connection("/imu0", "sensor_msgs/msg/Imu", typestore=get_typestore(Stores.ROS1_NOETIC))
        for i in range(n):
            frame = (b"imu", b"imu_link", b"base")[(i // 300) % 3]
            stamp = 1_700_000_000 * 10**9 + i * 5_000_000 + 123
            w.write(c, stamp + 7_000_000, struct.pack(f"<IIII{len(frame)}s4d9d3d9d3d9d", i, stamp // 10**9,
                                                      stamp % 10**9, len(frame), frame, 0.0, 0.0, 0.0, 1.0,
                                                      *(0.0,) * 9, *gyr[i], *(0.0,) * 9, *acc[i], *(0.0,) * 9))
    rec = read(p)
    assert len(rec) == n and not rec.breaks
    np.testing.assert_array_equal(rec.accel, acc)
    np.testing.assert_array_equal(rec.gyro, gyr)
    stamps = 1_700_000_000 * 10**9 + np.arange(n, dtype=np.int64) * 5_000_000 + 123     # the header's, not receipt's
    np.testing.assert_array_equal(rec.t_s, stamps // 10**9 + 1e-9 * (stamps % 10**9))
