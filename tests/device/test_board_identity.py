"""A virtual board's identity (MCU UID, ADXRS450 serial numbers) is a function of its target
and its seed (sim_identity_seed, firmware/boards/sim/sim_board.c): boards of different
targets with the same seed are different boards (on main an F103 and an F4 of one seed
shared a UID, and the device history merged them), and the same (target, seed) is the same
board on every start. Read as the firmware reports it (info), which is what the history keys on.
"""
from __future__ import annotations

import pytest
from imubench.device.link import Device
from imubench.device.sim import VirtualBench

SEED = 5
HOST_UID_SEED5 = "2c031631890f25c84db99906"   # main (81b285a), `imubench-sim --seed 5`: before targets counted


def _identity(target: str, seed: int) -> tuple[str, tuple[int, ...]]:
    with VirtualBench(speed=0, seed=seed, target=target) as vb, \
            Device.open(vb.port_url, timeout=10.0) as d:
        info = d.info()
        truth = vb.get_truth()
        uid = bytes(info.mcu_uid).hex()
        assert uid == vb.info["uid"]                                    # the UID the board was given
        assert list(info.gyro_sn) == [g["serial"] for g in truth["gyro"]]   # read over SPI
        return uid, tuple(info.gyro_sn)


@pytest.fixture(scope="module")
def ids() -> dict:
    return {t: _identity(t, SEED) for t in ("host", "f103", "f4")}


def test_each_target_is_a_different_board(ids):
    uids = {t: u for t, (u, _sn) in ids.items()}
    assert len(set(uids.values())) == 3, uids
    serials = [sn for _u, sns in ids.values() for sn in sns]
    assert len(set(serials)) == 9 and 0 not in serials, ids


def test_the_same_target_and_seed_is_the_same_board(ids):
    assert _identity("f103", SEED) == ids["f103"]
    other = _identity("f103", SEED + 1)
    assert other[0] != ids["f103"][0] and set(other[1]).isdisjoint(ids["f103"][1])


def test_the_host_build_keeps_its_identity(ids):
    """The host build's board is the one its seed named before targets counted (saved
    sessions and histories of host-build boards stay theirs): UID bytes from the seed's
    derivation, unchanged."""
    with VirtualBench(speed=0, seed=SEED, uid="00" * 12) as vb:
        assert vb.info["uid"] == "00" * 12                               # --uid still overrides
    assert ids["host"][0] == HOST_UID_SEED5
