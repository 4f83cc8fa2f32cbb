"""Both codecs, C and Python, against the shared vectors in protocol/vectors/."""
from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest
from conftest import ROOT
from imubench.wire import frame as P
from imubench.wire.protocol_gen import MESSAGES_BY_NAME

DOC = json.loads((ROOT / "protocol" / "vectors" / "vectors.json").read_text())
VECTORS = DOC["vectors"]
GOOD = [v for v in VECTORS if v["expect"] == "ok"]
BAD = [v for v in VECTORS if v["expect"] != "ok"]
ids = lambda vs: [v["name"] for v in vs]  # noqa: E731


def test_vectors_cover_every_message_and_every_reason():
    assert {v["message"]["type"] for v in GOOD} == set(MESSAGES_BY_NAME)
    assert {v["expect"] for v in BAD} == {r.value for r in P.FrameError}
    assert DOC["protocol_version"] == P.PROTOCOL_VERSION


def _flat(obj, prefix=""):
    out = {}
    for name, val in vars(obj).items():
        if name == "records":
            continue
        if hasattr(val, "FORMAT"):
            out.update(_flat(val, prefix + name + "."))
        else:
            out[prefix + name] = list(val) if isinstance(val, tuple) else val
    return out


def _same(got, want) -> bool:
    """Exact comparison: integers as integers, floats at float32 (the wire type)."""
    w = np.asarray(want)
    dtype = np.float32 if w.dtype.kind == "f" else np.float64
    return np.array_equal(np.asarray(got, dtype=np.float64).astype(dtype), w.astype(dtype))


# ----------------------------------------------------------------- Python codec
@pytest.mark.parametrize("v", GOOD, ids=ids(GOOD))
def test_python_decodes_good_vector(v):
    frame = P.parse_frame(bytes.fromhex(v["frame_hex"])[:-1])
    m = v["message"]
    assert (frame.seq, frame.timestamp_us) == (m["seq"], m["timestamp_us"])
    assert P.MESSAGES[frame.type].name == m["type"]
    msg = P.decode_message(frame.type, frame.payload)
    got = _flat(msg)
    assert set(got) == set(m["fields"])
    for k, want in m["fields"].items():
        assert got[k] == want if isinstance(want, str) else _same(got[k], want), k
    if "records" in m:
        assert len(msg.records) == len(m["records"])
        for rec, want in zip(msg.records, m["records"]):
            for k, val in want.items():
                assert _same(rec[k], val), k


@pytest.mark.parametrize("v", GOOD, ids=ids(GOOD))
def test_python_encodes_good_vector(v):
    m = v["message"]
    d = MESSAGES_BY_NAME[m["type"]]
    msg = d.cls()   # a default object, then every field set from the vector's flat list
    for k, val in m["fields"].items():
        target = msg
        *parents, leaf = k.split(".")
        for p in parents:
            target = getattr(target, p)
        setattr(target, leaf, tuple(val) if isinstance(val, list) else val)
    recs = None
    if "records" in m:
        recs = {k: np.array([r[k] for r in m["records"]]) for k in (m["records"][0] if m["records"] else {})}
    frame = P.encode(msg, m["seq"], m["timestamp_us"], records=recs if recs is not None else ({} if "records" in m else None))
    assert frame.hex() == v["frame_hex"]


@pytest.mark.parametrize("v", BAD, ids=ids(BAD))
def test_python_rejects_bad_vector_with_reason(v):
    with pytest.raises(P.ProtocolError) as e:
        P.parse_frame(bytes.fromhex(v["frame_hex"])[:-1])
    assert e.value.reason.value == v["expect"]


# ---------------------------------------------------------------------- C codec
def _run_harness(harness, text: str) -> list[str]:
    r = subprocess.run([str(harness)], input=text, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return r.stdout.splitlines()


def _fmt(val) -> str:
    if isinstance(val, str):
        return val.encode().hex()
    vals = val if isinstance(val, list) else [val]
    return " ".join(repr(float(x)) if isinstance(x, float) else str(x) for x in vals)


def _parse_harness_decode(lines):
    """-> list of (status line, fields dict, records dict-of-dicts)"""
    out, i = [], 0
    while i < len(lines):
        head = lines[i]
        i += 1
        if head.startswith("err"):
            out.append((head, None, None))
            continue
        fields, recs = {}, {}
        while lines[i] != "end":
            parts = lines[i].split(" ")
            if parts[0] == "f":
                fields[parts[1]] = parts[2:]
            else:
                recs.setdefault(int(parts[1]), {})[parts[2]] = parts[3:]
            i += 1
        i += 1
        out.append((head, fields, recs))
    return out


def _c_value(tokens: list[str], want):
    if isinstance(want, str):
        raw = bytes.fromhex(tokens[0]) if tokens else b""
        return raw.split(b"\0", 1)[0].decode()
    vals = [float(t) for t in tokens]
    return vals if isinstance(want, list) else vals[0]


def test_c_decodes_every_vector(c_harness):
    lines = _run_harness(c_harness, "".join(f"decode {v['frame_hex']}\n" for v in VECTORS))
    results = _parse_harness_decode(lines)
    assert len(results) == len(VECTORS)
    for v, (head, fields, recs) in zip(VECTORS, results):
        if v["expect"] != "ok":
            assert head == f"err {v['expect']}", v["name"]
            continue
        m = v["message"]
        assert head == f"ok {m['type']} {m['seq']} {m['timestamp_us']}", v["name"]
        assert set(fields) == set(m["fields"]), v["name"]
        for k, want in m["fields"].items():
            got = _c_value(fields[k], want)
            assert got == want if isinstance(want, str) else _same(got, want), (v["name"], k)
        for i, rec in enumerate(m.get("records", [])):
            for k, want in rec.items():
                assert _same(_c_value(recs[i][k], want), want), (v["name"], i, k)


def test_c_encodes_every_good_vector(c_harness):
    text = []
    for v in GOOD:
        m = v["message"]
        recs = m.get("records", [])
        text.append(f"encode {m['type']} {m['seq']} {m['timestamp_us']} {len(recs)}")
        text += [f"f {k} {_fmt(val)}" for k, val in m["fields"].items()]
        for i, r in enumerate(recs):
            text += [f"r {i} {k} {_fmt(val)}" for k, val in r.items()]
        text.append("end")
    lines = _run_harness(c_harness, "\n".join(text) + "\n")
    assert len(lines) == len(GOOD)
    for v, line in zip(GOOD, lines):
        assert line == f"hex {v['frame_hex']}", v["name"]


def test_worked_example_of_the_spec():
    """protocol/SPEC.md works one ping frame out by hand; the codec must agree."""
    from imubench.wire.protocol_gen import Ping
    assert P.encode(Ping(nonce=0x12345678), seq=7, timestamp_us=99).hex(" ") == \
        "04 05 01 07 02 63 01 01 09 78 56 34 12 03 36 ec 05 00"
    assert P.crc32c(bytes.fromhex("020107006300000078563412")) == 0x93B91A93
    spec = (ROOT / "protocol" / "SPEC.md").read_text()
    assert "04 05 01 07 02 63 01 01 09 78 56 34 12 03 36 ec 05 00" in spec
    assert P.crc32c(b"123456789") == 0xE3069283


def test_link_budget_frame_sizes_of_the_spec():
    """SPEC.md's link budget: 260 bytes per 16 raw samples, 92 per 4, 236 per 8 calibrated."""
    import numpy as np
    from imubench.wire.protocol_gen import BatchHeader, CalBatch, RawBatch

    def raw(n):
        recs = dict(accel_x_counts=np.full(n, 12345), accel_y_counts=np.full(n, -7), accel_z_counts=np.full(n, 256000),
                    status=np.zeros(n, int), gyro_counts=np.full((n, 3), 40))
        return len(P.encode(RawBatch(header=BatchHeader(sample_index=1, period_us=250, count=n, accel_range_g=2)),
                            1, 1, records=recs))

    cal = len(P.encode(CalBatch(header=BatchHeader(count=8, period_us=250, accel_range_g=2)), 1, 1,
                       records=dict(accel_mps2=np.full((8, 3), 9.8, np.float32),
                                    rate_rad_s=np.full((8, 3), 0.01, np.float32), status=np.zeros(8, int))))
    assert (raw(16), raw(4), cal) == (260, 92, 236)
    spec = (ROOT / "protocol" / "SPEC.md").read_text()
    assert "| raw | 16 | 260 | 16.25 |" in spec and "| calibrated | 8 | 236 | 29.5 |" in spec
    load_4k_921600 = 260 * 250 * 10 / 921600
    assert f"**{load_4k_921600:.1%}**".replace("%", " %") in spec


# ---------------------------------------------------------------------- time steps (SPEC.md, Header fields)
def test_time_steps_are_the_same_on_both_sides(c_harness):
    """The signed step between two u32 device times, exactly 2^31 included (a step back), from
    the Python decoder and the C helper ib_time_step_us, against the shared vectors."""
    from imubench.wire.decoder import time_step_us
    steps = DOC["time_steps"]
    assert any(s["step_us"] == -(1 << 31) for s in steps)                 # the boundary is in the set
    assert [time_step_us(s["now"], s["prev"]) for s in steps] == [s["step_us"] for s in steps]
    lines = _run_harness(c_harness, "".join(f"step {s['now']} {s['prev']}\n" for s in steps))
    assert lines == [f"step {s['step_us']}" for s in steps]
