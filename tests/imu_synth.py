"""A synthetic Ferraris session of a 6-axis IMU with known errors, for the from-file tests:
rests on the six faces joined by smooth rotations, then one full turn about X, Y and Z while
that axis points up. The truth: u = M·x + b per triad (docs/conventions.md), in SI."""
from __future__ import annotations

import math

import numpy as np

G0 = 9.80665


def _rodrigues(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def up_in_body(c):
    return c.T @ np.array([0.0, 0.0, 1.0])


def ferraris_truth(seed=0):
    rng = np.random.default_rng(seed)
    ma = np.eye(3) + np.diag(rng.normal(0, 0.01, 3)) + np.tril(rng.normal(0, 0.004, (3, 3)), -1) \
        + np.triu(rng.normal(0, 0.004, (3, 3)), 1)
    mg = np.eye(3) + np.diag(rng.normal(0, 0.02, 3)) + rng.normal(0, 0.005, (3, 3)) * (1 - np.eye(3))
    return {"accel_m": ma, "accel_b": rng.normal(0, 0.1, 3), "gyro_m": mg, "gyro_b": np.radians(rng.normal(0, 0.5, 3))}


def turned(c, ax, rate, fs):
    """The body attitude c carried through a turn about the body axis ax (unit) at rate (rad/s,
    one value a sample): (c at its end, the specific force in m/s² of each sample)."""
    a_out = np.empty((len(rate), 3))
    for k in range(len(rate)):
        c = c @ _rodrigues(ax, rate[k] / fs)
        a_out[k] = up_in_body(c) * G0
    return c, a_out


def ferraris_session(fs=100.0, seed=0, truth=None, rest_s=4.0, turn_s=4.0, accel_noise=0.004,
                     gyro_noise=np.radians(0.05), both_ways=False, edges=False):
    """(accel m/s², gyro rad/s (n, 3) each, truth dict, events): the measured u of both triads."""
    truth = truth or ferraris_truth(seed)
    rng = np.random.default_rng(seed + 1)
    c = np.eye(3)                     # body -> world; +Z up
    acc, gyr, events = [], [], []

    def rest(sec):
        n = int(sec * fs)
        f = up_in_body(c) * G0
        acc.append(np.repeat(f[None, :], n, 0))
        gyr.append(np.zeros((n, 3)))
        events.append(("rest", sum(len(a) for a in acc) - n, sum(len(a) for a in acc)))

    def rot(axis_body, deg, sec):
        nonlocal c
        n = int(sec * fs)
        t = (np.arange(n) + 0.5) / n
        w = (1 - np.cos(2 * np.pi * t))           # raised cosine, integrates to n / n = 1 over [0, 1]
        rate = np.radians(deg) / sec * w * (sec * fs / n)   # rad/s, integral = deg (n = sec·fs rounded down)
        ax = np.asarray(axis_body, float) / np.linalg.norm(axis_body)
        c, a_out = turned(c, ax, rate, fs)
        acc.append(a_out)
        gyr.append(rate[:, None] * ax[None, :])
        events.append(("rot", sum(len(a) for a in acc) - n, sum(len(a) for a in acc)))

    rest(rest_s)                 # +Z
    if edges:                    # attitudes between the faces (cube edges and corners), for --method multi
        for ax, ang in (([1, 0, 0], 45), ([1, 0, 0], -90), ([1, 0, 0], 45), ([0, 1, 0], 45), ([0, 1, 0], -90),
                        ([0, 1, 0], 45), ([1, 1, 0], 55), ([1, 1, 0], -55), ([1, -1, 0], 55), ([1, -1, 0], -55),
                        ([1, 0, 0], 135), ([1, 0, 0], -135), ([0, 1, 0], 135), ([0, 1, 0], -135)):
            rot(ax, ang, 1.5)
            rest(rest_s / 2)
    if both_ways:                # each axis turned both ways while horizontal: the rotation method sees M
        for ax in ([1, 0, 0], [0, 1, 0]):
            for ang in (-90, 90, 90, -90):
                rot(ax, ang, 1.5)
                rest(rest_s / 2)
        rot([0, 1, 0], 90, 1.5)  # X up ... Z horizontal
        rest(rest_s / 2)
        for ang in (90, -90, -90, 90):
            rot([0, 0, 1], ang, 1.5)
            rest(rest_s / 2)
        rot([0, 1, 0], -90, 1.5)  # back to +Z
        rest(rest_s / 2)
    rot([1, 0, 0], 180, 2.0)
    rest(rest_s)                 # -Z
    rot([1, 0, 0], 90, 1.5)
    rest(rest_s)                 # ±Y
    rot([1, 0, 0], 180, 2.0)
    rest(rest_s)                 # ∓Y
    rot([1, 0, 0], 90, 1.5)      # back to +Z
    rot([0, 1, 0], 90, 1.5)
    rest(rest_s)                 # ±X
    rot([0, 1, 0], 180, 2.0)
    rest(rest_s)                 # ∓X
    # turns: the up axis of this rest, then Y and Z up
    for target in ([1, 0, 0], [0, 1, 0], [0, 0, 1]):
        up = up_in_body(c)
        tgt = np.array(target, float)
        if up @ tgt < 0.99:
            ax = np.cross(up, tgt)
            if np.linalg.norm(ax) < 1e-9:
                ax = np.array([0.0, 0.0, 1.0]) if abs(tgt[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
            ang = math.degrees(math.acos(np.clip(up @ tgt, -1, 1)))
            # rotating the body about ax by -ang carries up onto tgt
            rot(ax, -ang, 1.5)
            rest(rest_s)
        rot(tgt, 360.0, turn_s)
        rest(rest_s)
    x_a = np.concatenate(acc)
    x_g = np.concatenate(gyr)
    u_a = x_a @ truth["accel_m"].T + truth["accel_b"] + rng.normal(0, accel_noise, x_a.shape)
    u_g = x_g @ truth["gyro_m"].T + truth["gyro_b"] + rng.normal(0, gyro_noise, x_g.shape)
    return u_a, u_g, truth, events


def write_csv(path, acc_g, gyr_dps, fs, header=("t_ms", "acc_x", "acc_y", "acc_z", "gyr_x", "gyr_y", "gyr_z"),
              t=None):
    t = np.arange(len(acc_g)) / fs * 1e3 if t is None else t
    np.savetxt(path, np.column_stack([t, acc_g, gyr_dps]), delimiter=",", header=",".join(header), comments="",
               fmt="%.9g")
    return path


# ------------------------------------------------------------------ the shapes of other people's files (issues 32, 40)
def write_table(path, rows, *, delim=" ", fmt="%.9g", header=None, comment_header=None, preamble=(), line_end="\n"):
    """A text table as loggers write them: preamble lines (metadata such as ``Fs,100``), a header
    row or a ``# name name ...`` comment line, then the rows; line_end is what ends each line
    (" \\n": a space before the newline)."""
    out = [*preamble]
    if comment_header is not None:
        out.append("# " + " ".join(comment_header))
    if header is not None:
        out.append(delim.join(header))
    out += [delim.join(fmt % v for v in row) for row in np.asarray(rows)]
    with open(path, "w") as f:
        f.write("".join(line + line_end for line in out))
    return path


def unsigned_counts(x, per_unit, bits=16):
    """Signed readings x (in a physical unit) as a register of `bits` read unsigned: round(x · per_unit)
    + 2^(bits−1), held within 0 .. 2^bits − 1."""
    half = 2 ** (bits - 1)
    return np.clip(np.round(np.asarray(x) * per_unit) + half, 0, 2 * half - 1)


def write_imutk_pair(directory, stem, t_s, acc, gyr):
    """imu_tk's ASCII pair: STEM_acc.mat and STEM_gyro.mat, each line 't x y z' (t in seconds)."""
    from pathlib import Path
    d = Path(directory)
    a, g = d / f"{stem}_acc.mat", d / f"{stem}_gyro.mat"
    np.savetxt(a, np.column_stack([t_s, acc]), fmt="%.9g")
    np.savetxt(g, np.column_stack([t_s, gyr]), fmt="%.9g")
    return a, g


def logger_times(n, fs, t0=1535632344.47, late_s=0.005, late_every=8, resolution_s=0.001, seed=0):
    """Time stamps of a logging PC: the samples are uniform at fs, none missing, but stamped at the
    PC's clock resolution and one in `late_every` (at random) stamped late_s late, so the steps
    alternate long and short around 1/fs. Unix time (seconds) from t0."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs
    late = rng.random(n) < 1.0 / late_every
    late[1:] &= ~late[:-1]                  # never two late in a row: each long step is made up by the next
    return t0 + np.floor((t + late * late_s) / resolution_s) * resolution_s


def _toward(u, tgt):
    """(axis, angle rad) of the body rotation that carries the body-frame up vector u onto tgt."""
    u, tgt = np.asarray(u, float) / np.linalg.norm(u), np.asarray(tgt, float) / np.linalg.norm(tgt)
    ax = np.cross(u, tgt)
    s = np.linalg.norm(ax)
    ang = math.atan2(s, float(u @ tgt))
    if s < 1e-9:
        if ang < 1e-9:
            return np.array([1.0, 0.0, 0.0]), 0.0
        ax = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
    return ax / np.linalg.norm(ax), -ang


def tilted(direction, max_deg, rng):
    """direction (a unit vector) tilted by a uniform random angle up to max_deg, random azimuth."""
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    p = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
    p /= np.linalg.norm(p)
    return _rodrigues(_rodrigues(d, rng.uniform(0, 2 * math.pi)) @ p, math.radians(rng.uniform(0, max_deg))) @ d


FACES6 = ([0, 0, 1], [0, 0, -1], [0, 1, 0], [0, -1, 0], [1, 0, 0], [-1, 0, 0])
CORNERS4 = ([1, 1, 1], [-1, -1, 1], [1, -1, -1], [-1, 1, -1])
EDGES_XZ_YZ = ([1, 0, 1], [-1, 0, -1], [0, 1, 1], [0, -1, -1])     # no pose sees x and y together


def handheld_session(ups, fs=100.0, seed=0, truth=None, rest_s=4.0, move_s=1.5, tilt_deg=0.0, drift_mg=0.0,
                     accel_noise=0.004, gyro_noise=np.radians(0.05)):
    """A hand-held recording: rests with the board's up axis (body frame) along each of `ups`,
    joined by smooth rotations. Within rest i the board tilts slowly by tilt_deg[i] (about a
    random horizontal axis, at a constant rate) and the specific force's magnitude drifts
    linearly by drift_mg[i], from −drift/2 to +drift/2 about the truth (a hand's wander, not a
    sensor's drift; scalars apply to every rest). Returns (accel m/s², gyro rad/s,
    truth, events) as ferraris_session; events hold ("rest", start, stop, tilt_deg, drift_mg)."""
    truth = truth or ferraris_truth(seed)
    rng = np.random.default_rng(seed + 7)
    m = len(ups)
    tilt = np.broadcast_to(np.asarray(tilt_deg, float), (m,))
    drift = np.broadcast_to(np.asarray(drift_mg, float), (m,))
    c = np.eye(3)
    ax0, a0 = _toward(up_in_body(c), ups[0])
    c = c @ _rodrigues(ax0, a0) if a0 else c
    acc, gyr, events = [], [], []
    n_done = 0

    def rotate(ax, ang, n):
        nonlocal c
        t = (np.arange(n) + 0.5) / n
        w = 1 - np.cos(2 * np.pi * t)
        rate = ang / (n / fs) * w
        c, out = turned(c, ax, rate, fs)
        return out, rate[:, None] * ax[None, :]

    for i, up in enumerate(ups):
        if i:
            ax, ang = _toward(up_in_body(c), up)
            a, g = rotate(ax, ang, int(move_s * fs))
            acc.append(a)
            gyr.append(g)
            n_done += len(a)
        n = int(rest_s * fs)
        u = up_in_body(c)
        h = np.cross(u, rng.normal(size=3))
        h /= np.linalg.norm(h)
        rate = math.radians(tilt[i]) / rest_s
        a = np.empty((n, 3))
        for k in range(n):
            c = c @ _rodrigues(h, rate / fs)
            a[k] = up_in_body(c) * G0 * (1.0 + drift[i] * 1e-3 * ((k + 0.5) / n - 0.5))
        acc.append(a)
        gyr.append(np.repeat((rate * h)[None, :], n, 0))
        events.append(("rest", n_done, n_done + n, float(tilt[i]), float(drift[i])))
        n_done += n
    x_a, x_g = np.concatenate(acc), np.concatenate(gyr)
    nrng = np.random.default_rng(seed + 1)
    u_a = x_a @ truth["accel_m"].T + truth["accel_b"] + nrng.normal(0, accel_noise, x_a.shape)
    u_g = x_g @ truth["gyro_m"].T + truth["gyro_b"] + nrng.normal(0, gyro_noise, x_g.shape)
    return u_a, u_g, truth, events


def spread_ups(n=26):
    """The 26 attitudes of a cube's faces, edges and corners (first n), as up vectors."""
    out = []
    for v in ([1, 0, 0], [0, 1, 0], [0, 0, 1]):
        for s in (1, -1):
            out.append(np.array(v, float) * s)
    for i in range(3):
        for j in range(i + 1, 3):
            for si in (1, -1):
                for sj in (1, -1):
                    v = np.zeros(3)
                    v[i], v[j] = si, sj
                    out.append(v / math.sqrt(2))
    for sx in (1, -1):
        for sy in (1, -1):
            for sz in (1, -1):
                out.append(np.array([sx, sy, sz], float) / math.sqrt(3))
    return out[:n]


# ------------------------------------------------------------------ issue 32: a gyro that clips
# 18 motions between 19 rests of 2 s: ±90° about X, then Y, both ways while horizontal, Z off the
# vertical, then flips about X; every rest a face, so the accelerometer sees all six.
CLIP_PLAN = (((1, 0, 0), -90), ((1, 0, 0), 90), ((1, 0, 0), 90), ((1, 0, 0), -90),
             ((0, 1, 0), -90), ((0, 1, 0), 90), ((0, 1, 0), 90), ((0, 1, 0), -90),
             ((0, 1, 0), 90), ((0, 0, 1), 90), ((0, 0, 1), -90), ((0, 0, 1), -90), ((0, 0, 1), 90),
             ((0, 1, 0), -90), ((1, 0, 0), 180), ((1, 0, 0), 90), ((1, 0, 0), 180), ((1, 0, 0), 90))


def motion_session(plan, fs=100.0, seed=0, truth=None, rest_s=2.0, peak_dps=120.0, fast=(), fast_peak_dps=320.0,
                   accel_noise=0.004, gyro_noise=np.radians(0.05)):
    """(accel m/s², gyro rad/s, truth, events): rests joined by the plan's rotations (body axis, degrees),
    each a raised cosine peaking at peak_dps, those whose index is in `fast` at fast_peak_dps."""
    truth = truth or ferraris_truth(seed)
    rng = np.random.default_rng(seed + 1)
    c = np.eye(3)
    acc, gyr, events = [], [], []

    def rest():
        n = int(rest_s * fs)
        acc.append(np.repeat((up_in_body(c) * G0)[None, :], n, 0))
        gyr.append(np.zeros((n, 3)))
        events.append(("rest", sum(len(a) for a in acc) - n, sum(len(a) for a in acc)))

    rest()
    for j, (axis, deg) in enumerate(plan):
        sec = 2.0 * abs(deg) / (fast_peak_dps if j in fast else peak_dps)   # the raised cosine's peak: 2·angle/T
        n = int(round(sec * fs))
        t = (np.arange(n) + 0.5) / n
        rate = np.radians(deg) / (n / fs) * (1 - np.cos(2 * np.pi * t))
        ax = np.asarray(axis, float) / np.linalg.norm(axis)
        c, a_out = turned(c, ax, rate, fs)
        acc.append(a_out)
        gyr.append(rate[:, None] * ax[None, :])
        events.append(("rot", sum(len(a) for a in acc) - n, sum(len(a) for a in acc)))
        rest()
    x_a, x_g = np.concatenate(acc), np.concatenate(gyr)
    u_a = x_a @ truth["accel_m"].T + truth["accel_b"] + rng.normal(0, accel_noise, x_a.shape)
    u_g = x_g @ truth["gyro_m"].T + truth["gyro_b"] + rng.normal(0, gyro_noise, x_g.shape)
    return u_a, u_g, truth, events


def clipped_gyro_session(fast, range_dps=250.0, fs=100.0, seed=0):
    """motion_session(CLIP_PLAN) whose motions in `fast` peak at 320 °/s, read by a gyro whose range is
    ±range_dps: its output held at the range (as a saturated converter holds its code)."""
    ua, ug, truth, events = motion_session(CLIP_PLAN, fs=fs, seed=seed, fast=fast)
    r = np.radians(range_dps)
    return ua, np.clip(ug, -r, r), truth, events
