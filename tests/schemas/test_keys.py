from __future__ import annotations

import pytest

from schemas import keys
from schemas import messages as m
from schemas.keys import KeyExprError


def test_key_layout_and_types():
    assert keys.meas_head("rural") == "cvvc/rural/meas/head"
    assert keys.cmd("rural", "pv", "pv1") == "cvvc/rural/cmd/pv/pv1"
    assert keys.message_type_for_key(keys.meas_pv("rural", "pv1")) is m.PvFrame
    assert keys.message_type_for_key(keys.meas_vr("rural", "vr1a")) is m.RegFrame
    assert keys.message_type_for_key(keys.ack("rural", "vr", "x")) is m.Ack
    assert keys.message_type_for_key(keys.agent_decision("rural")) is m.Decision
    assert keys.message_type_for_key("other/rural/meas/head") is None
    assert keys.parse_device_key("cvvc/rural/cmd/pv/pv1") == ("rural", "cmd", "pv", "pv1")


@pytest.mark.parametrize("bad", ["", "a/b", "x*", "$y", "a" * 65, "sp ace"])
def test_bad_ids_rejected(bad):
    with pytest.raises(KeyExprError):
        keys.meas_pv("rural", bad)


def test_capacitor_keys_and_types():
    assert keys.meas_cap("ieee123", "c83") == "cvvc/ieee123/meas/cap/c83"
    assert keys.meas_cap("ieee123") == "cvvc/ieee123/meas/cap/*"
    assert keys.cmd("ieee123", "cap", "c83") == "cvvc/ieee123/cmd/cap/c83"
    assert keys.ack("ieee123", "cap", "c83") == "cvvc/ieee123/ack/cap/c83"
    assert keys.alive("ieee123", "cap", "c83") == "cvvc/ieee123/alive/cap/c83"
    assert keys.message_type_for_key(keys.meas_cap("ieee123", "c83")) is m.CapFrame
    assert keys.message_type_for_key(keys.cmd("ieee123", "cap", "c83")) is m.CapCommand
    assert keys.message_type_for_key(keys.ack("ieee123", "cap", "c83")) is m.Ack
    with pytest.raises(KeyExprError):
        keys.meas_cap("ieee123", "c/83")
