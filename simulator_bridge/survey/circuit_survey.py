"""Read-only looks at a plain OpenDSS model, each in a context of its own that is dropped on return.

:func:`survey_circuit` describes a compiled model as ``survey.py``'s typed data (for ``cvvc feeder scaffold`` and
``feeder info``); :func:`opendss_snapshot` is OpenDSS's own solution of a model with its own controls on (for
golden comparisons with the engine).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from simulator_bridge.errors import EngineError
from simulator_bridge.opendss.dss_context import DSS_LIFECYCLE, DssException, compile_feeder, new_context
from simulator_bridge.survey.survey import (
    CircuitSurvey,
    SurveyBus,
    SurveyCapacitor,
    SurveyEdge,
    SurveyLoad,
    SurveyMeter,
    SurveyPvSystem,
    SurveyRegControl,
)

__all__ = ["OpenDssSnapshot", "opendss_snapshot", "survey_circuit"]


@dataclass(frozen=True)
class OpenDssSnapshot:
    """OpenDSS's own solution of a plain model (its own controls on), for golden comparisons.

    Attributes
    ----------
    node_names : OpenDSS ``AllNodeNames``, lower case.
    v_pu : (n_nodes,) node voltage magnitudes [pu of each bus's L-N base].
    taps : {regcontrol name (lower case): tap position} after OpenDSS's control iterations.
    """

    node_names: tuple[str, ...]
    v_pu: np.ndarray
    taps: dict[str, int]


def opendss_snapshot(master: str | Path, *, tolerance: float = 1e-8) -> OpenDssSnapshot:
    """Compile ``master`` as it is, solve one snapshot with OpenDSS's own (static) controls, and read it.

    Raises
    ------
    EngineError
        The model does not compile or the snapshot does not converge.
    """
    ctx = new_context()
    cwd = os.getcwd()
    try:
        with DSS_LIFECYCLE:
            ctx.Text.Command(f'compile "{Path(master).resolve()}"')
        ctx.Text.Command(f"set tolerance={tolerance:.3g}")
        ctx.Text.Command("set maxcontroliter=100")
        ctx.Text.Command("set maxiterations=100")
        ctx.Solution.Solve()
    except DssException as e:
        raise EngineError(f"{master}: OpenDSS snapshot failed: {e}") from e
    finally:
        os.chdir(cwd)
    if not ctx.Solution.Converged():
        raise EngineError(f"{master}: OpenDSS snapshot did not converge")
    taps = {}
    i = ctx.RegControls.First()
    while i > 0:
        taps[ctx.RegControls.Name().lower()] = int(ctx.RegControls.TapNumber())
        i = ctx.RegControls.Next()
    return OpenDssSnapshot(
        node_names=tuple(n.lower() for n in ctx.Circuit.AllNodeNames()),
        v_pu=np.asarray(ctx.Circuit.AllBusMagPu(), dtype=float),
        taps=taps,
    )


_CAPCONTROL_MODES = {0: "current", 1: "voltage", 2: "kvar", 3: "time", 4: "pf"}  # CapControls.Mode()

def survey_circuit(master: str | Path, *, extra_commands: tuple[str, ...] | list[str] = ()) -> CircuitSurvey:
    """Compile ``master`` in a context of its own (plus ``extra_commands``) and read what it holds.

    Read only: nothing is solved, nothing is changed; the context is dropped on return.

    Raises
    ------
    EngineError
        The model does not compile, an extra command is rejected, or the circuit is empty.
    """
    master = Path(master).resolve()
    d = new_context()
    with DSS_LIFECYCLE:
        compile_feeder(d, master, extra_commands)

    def bus_of(spec: str) -> str:
        return spec.split(".")[0].lower()

    def phases_of(spec: str, n: int) -> int:
        parts = [p for p in spec.split(".")[1:] if p.isdigit() and 1 <= int(p) <= 3]
        return len(parts) if parts else n

    buses = []
    for name in d.Circuit.AllBusNames():
        d.Circuit.SetActiveBus(name)
        buses.append(SurveyBus(name.lower(), float(d.Bus.kVBase()),
                               tuple(sorted(int(n) for n in d.Bus.Nodes() if 1 <= int(n) <= 3))))
    line_z: dict[str, complex] = {}
    i = d.Lines.First()
    while i > 0:
        n = int(d.Lines.Phases())
        z = (np.asarray(d.Lines.RMatrix(), float) + 1j * np.asarray(d.Lines.XMatrix(), float)).reshape(n, n)
        z1 = np.mean(np.diag(z)) - (np.mean(z[~np.eye(n, dtype=bool)]) if n > 1 else 0.0)
        line_z[f"line.{d.Lines.Name().lower()}"] = complex(z1 * d.Lines.Length())
        i = d.Lines.Next()
    edges = []
    i = d.PDElements.First()
    while i > 0:
        name = d.CktElement.Name().lower()
        specs = list(d.CktElement.BusNames())
        kind = name.split(".")[0]
        if d.CktElement.Enabled() and kind != "capacitor":
            n_ph = int(d.CktElement.NumPhases())
            for a in range(len(specs)):
                for b in range(a + 1, len(specs)):
                    if bus_of(specs[a]) != bus_of(specs[b]):
                        edges.append(SurveyEdge(name, kind, bus_of(specs[a]), bus_of(specs[b]),
                                                min(phases_of(specs[a], n_ph), phases_of(specs[b], n_ph)),
                                                line_z.get(name, 0j)))
        i = d.PDElements.Next()
    d.Circuit.SetActiveElement("Vsource.source")
    source_bus = bus_of(d.CktElement.BusNames()[0])
    d.Vsources.Name("source")
    source_kv, source_pu = float(d.Vsources.BasekV()), float(d.Vsources.PU())

    regs = []
    i = d.RegControls.First()
    while i > 0:
        name, xf, w = d.RegControls.Name().lower(), d.RegControls.Transformer().lower(), int(d.RegControls.Winding())
        vreg, band = float(d.RegControls.ForwardVreg()), float(d.RegControls.ForwardBand())
        delay, tapdelay = float(d.RegControls.Delay()), float(d.RegControls.TapDelay())
        monitored = d.RegControls.MonitoredBus().strip().lower()
        d.Circuit.SetActiveElement(f"Transformer.{xf}")
        specs = list(d.CktElement.BusNames())
        n_ph = int(d.CktElement.NumPhases())
        other = specs[1] if w == 1 and len(specs) > 1 else specs[0]
        regs.append(SurveyRegControl(name, xf, w, bus_of(specs[w - 1]), bus_of(other), phases_of(specs[w - 1], n_ph),
                                     vreg, band, delay, tapdelay, monitored))
        i = d.RegControls.Next()
    controls: dict[str, tuple[str, str]] = {}
    i = d.CapControls.First()
    while i > 0:
        controls[d.CapControls.Capacitor().lower()] = (
            d.CapControls.Name().lower(), _CAPCONTROL_MODES.get(int(d.CapControls.Mode()), "unknown"))
        i = d.CapControls.Next()
    caps = []
    i = d.Capacitors.First()
    while i > 0:
        name = d.Capacitors.Name().lower()
        spec = d.CktElement.BusNames()[0]
        ctl = controls.get(name)
        caps.append(SurveyCapacitor(name, bus_of(spec), phases_of(spec, int(d.CktElement.NumPhases())),
                                    float(d.Capacitors.kvar()), float(d.Capacitors.kV()),
                                    ctl[0] if ctl else None, ctl[1] if ctl else None))
        i = d.Capacitors.Next()
    pvs = []
    i = d.PVsystems.First()
    while i > 0:
        spec = d.CktElement.BusNames()[0]
        name = d.PVsystems.Name().lower()
        d.Text.Command(f"? pvsystem.{name}.kv")
        try:
            kv = float(d.Text.Result())
        except ValueError:
            kv = 0.0
        pvs.append(SurveyPvSystem(name, bus_of(spec), phases_of(spec, int(d.CktElement.NumPhases())),
                                  float(d.PVsystems.kVARated()), float(d.PVsystems.Pmpp()), kv))
        i = d.PVsystems.Next()
    loads = []
    i = d.Loads.First()
    while i > 0:
        loads.append(SurveyLoad(d.Loads.Name().lower(), bus_of(d.CktElement.BusNames()[0]), float(d.Loads.kW())))
        i = d.Loads.Next()
    meters = []
    i = d.Meters.First()
    while i > 0:
        meters.append(SurveyMeter(d.Meters.Name().lower(), d.Meters.MeteredElement().lower(),
                                  int(d.Meters.MeteredTerminal())))
        i = d.Meters.Next()
    return CircuitSurvey(
        master=str(master), circuit=d.Circuit.Name().lower(), source_bus=source_bus, source_kv_ll=source_kv,
        source_pu=source_pu, buses=tuple(buses), edges=tuple(edges),
        elements=frozenset(e.lower() for e in d.Circuit.AllElementNames()), regcontrols=tuple(regs),
        capacitors=tuple(caps), pvsystems=tuple(pvs), loads=tuple(loads), meters=tuple(meters),
        node_count=len(d.Circuit.AllNodeNames()),
    )
