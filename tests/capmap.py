"""IEEE 13 with its two capacitor banks as field devices: the device map shared by the bank tests."""

from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
FEEDER = "ieee13caps"


def write_ieee13_caps_map(folder: Path) -> Path:
    """IEEE 13's own map plus its banks, written into ``folder``: cap1 (600 kvar, three-phase) and cap2 (100 kvar,
    one phase, no control).

    cap1's voltage CapControl (on a 120 V PT base) switches ON below 140 V and OFF above 150 V: on this feeder it
    always wants the bank closed, so a bank opened by a command that expires closes again under local control.
    """
    base = (REPO / "feeders" / "ieee13.toml").read_text()
    shared = (REPO.parent / "shared" / "feeders" / "ieee13" / "IEEE13Nodeckt.dss").resolve()
    text = base.replace('name = "ieee13"', f'name = "{FEEDER}"').replace(
        'master = "../../shared/feeders/ieee13/IEEE13Nodeckt.dss"',
        f'master = "{shared.as_posix()}"\nextra_commands = ["New CapControl.cc1 Capacitor=Cap1 Element=Line.692675 '
        'Terminal=1 Type=Voltage PTratio=20 ON=140 OFF=150 Delay=30 DelayOFF=30"]')
    text += ('\n[[capacitor]]\nid = "cap1"\ncapacitor = "Cap1"\ncapcontrol = "cc1"\ncost_per_switch = 2.0\n'
             '\n[[capacitor]]\nid = "cap2"\ncapacitor = "Cap2"\n')
    path = Path(folder) / f"{FEEDER}.toml"
    path.write_text(text)
    return path
