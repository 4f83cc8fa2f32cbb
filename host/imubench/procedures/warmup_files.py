"""Several warm-ups fitted together (the faces of a cube, `imubench thermal --fit-warmups`):
each run's bins re-cut from its capture.bin, the fit shared across the faces
(imubench.procedures.warmup.fit_bins; docs/thermal.md, "The warm-up method")."""
from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from imubench.analysis.thermal import POSES
from imubench.analysis.thermal_poly import Binned
from imubench.files import MAX_JSON_BYTES, read_text
from imubench.procedures.warmup import CAPTURE_NAME, WarmupConfig, WarmupError, _State, fit_bins
from imubench.results.thermal_warmup import WarmupRecord
from imubench.wire.board_parts import BoardParts
from imubench.wire.decoder import StreamDecoder


def load_warmup(directory) -> tuple[np.ndarray, Binned, dict]:
    """A warm-up directory's face and bins: the bins re-cut from capture.bin (every sample, also
    of a run that crashed), or those thermal.json kept when the capture is gone."""
    d = Path(directory)
    try:
        data = json.loads(read_text(d / WarmupRecord.NAME, MAX_JSON_BYTES, "thermal.json"))
    except (OSError, ValueError) as e:
        raise WarmupError(f"{d}: no readable thermal.json of a warm-up ({e})") from None
    if not isinstance(data, dict) or data.get("kind") != "imubench thermal warmup":
        raise WarmupError(f"{d / WarmupRecord.NAME} is not a warm-up (kind {data.get('kind') if isinstance(data, dict) else '?'!r})")
    cfg = data.get("config") or {}
    face = cfg.get("face", "+z")
    if face not in POSES:
        raise WarmupError(f"{d}: face {face!r} unknown")
    bin_s = float(cfg.get("bin_s") or 10.0)
    cap = d / (data.get("capture") or CAPTURE_NAME)
    b = None
    if cap.is_file():
        # piece by piece: a 4-hour capture is ~90 MB of frames; only the bins are kept
        st = _State(WarmupConfig(bin_s=bin_s, stop_window_s=max(300.0, 3 * bin_s)))
        dec = StreamDecoder()
        with open(cap, "rb") as fh:
            while chunk := fh.read(1 << 20):
                dec.feed(chunk)
                blk = dec.take_samples(False)
                if blk is not None and len(blk):
                    st.feed(blk)
        if st.bins:
            b = st.binned()
    if b is None:
        bj = data.get("bins")
        if not bj:
            raise WarmupError(f"{d}: neither {cap.name} nor bins in thermal.json")
        b = Binned(np.asarray(bj["t_s"], float), np.asarray(bj["temp_c"], float),
                   np.column_stack([bj["accel_mps2"], bj["gyro_rad_s"]]),
                   np.column_stack([bj["accel_sigma_mps2"], bj["gyro_sigma_rad_s"]]), np.asarray(bj["n"], int))
    return np.array(POSES[face], float), b, data


def fit_warmups(dirs: Sequence, t_ref_c: float | None = None, max_order: int = 3) -> tuple[dict, dict, list]:
    """Fit several warm-ups together (faces of a cube): (fits, t_ref, the thermal.json of each).
    t_ref: given, or the first run's."""
    loaded = [load_warmup(x) for x in dirs]
    if t_ref_c is None:
        tr = loaded[0][2].get("t_ref_c") or {"accel": 25.0, "gyro": 25.0}
        t_ref = {"accel": float(tr["accel"]), "gyro": float(tr["gyro"])}
    else:
        t_ref = {"accel": float(t_ref_c), "gyro": float(t_ref_c)}
    uids = {(x[2].get("device") or {}).get("mcu_uid") for x in loaded}
    if len(uids) > 1:
        raise WarmupError(f"the warm-ups come from different devices ({', '.join(sorted(str(u) for u in uids))})")
    parts = BoardParts.of_device(loaded[0][2].get("device"))     # one device: its parts, as it reported them
    return fit_bins([(d, b) for d, b, _ in loaded], t_ref, max_order, parts), t_ref, [x[2] for x in loaded]
