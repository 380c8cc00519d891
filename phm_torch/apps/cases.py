"""``phm-cases``: the virtual bench: the nominal actuator and a list of faulty ones, side by side.

All cases (nominal first) are simulated in ONE batched simulator call (an HF call costs about the same
for 1 or ~100 actuators). Written to ``out_dir``:

* ``<case>.csv`` for the nominal run and every case (measurement CSV format, noise as configured);
* ``<case>.png``: the case overlaid on the nominal run;
* ``metrics.json``: per case the fault vector, the NRMSE of the current and of the position against the
  nominal run (noise-free signals, RMS difference / range of the nominal signal, fractions), tracking
  error and peak current;
* ``.hydra/`` (composed config) and ``run.log`` when run from the command line.

Examples::

    phm-cases                                             # HF, paper chirp, results/cases
    phm-cases fidelity=lf out_dir=results/lf
    phm-cases 'only=[k1_friction,k8_gain_drift]'          # a subset of the configured cases
    phm-cases '+cases.k2_full={k2: 1.0}'                  # one more case
    phm-cases '~cases' '+cases={k1_full: {k1: 1.0}, k2_full: {k2: 1.0}}'   # other cases only
"""

from __future__ import annotations

import json
import logging
import math
import re
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from ..faults import N_FAULTS
from ..io import write_measurement
from ..metrics import nrmse
from ..sensor_noise import add_sensor_noise
from ..simulator import EMASimulator
from . import common
from .simulate import CSV_COLUMNS

log = logging.getLogger(__name__)

_CASE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
_FAULT_KEY = re.compile(r"^k([1-9])$")


def parse_cases(node: Any, nominal: list[float], only: Any = None) -> dict[str, list[float]]:
    """Fault vectors of the cases.

    Each case is either ``{kN: value, ...}`` (the nominal vector with those entries replaced) or a full
    list of 8 values. Names must be usable as file names and may not be ``nominal``. ``only``: optional
    list of case names to keep (in the order of ``cases``).
    """
    spec = common.plain(node)
    if spec is None:
        spec = {}
    if not isinstance(spec, Mapping):
        raise ValueError(f"cases must be a mapping {{name: {{kN: value}}}}, got {spec!r}")
    only = common.plain(only)
    if only is not None:
        if not isinstance(only, (list, tuple)):
            raise ValueError(f"only must be a list of case names or null, got {only!r}")
        unknown = [str(n) for n in only if str(n) not in spec]
        if unknown:
            raise ValueError(f"only: unknown case(s) {unknown}; cases: {list(spec)}")
        spec = {name: case for name, case in spec.items() if name in {str(n) for n in only}}
    cases: dict[str, list[float]] = {}
    for name, case in spec.items():
        name = str(name)
        if not _CASE_NAME.match(name) or name == "nominal":
            raise ValueError(f"cases: invalid case name {name!r} (letters, digits, '_', '.', '-'; not 'nominal')")
        if isinstance(case, (list, tuple)):
            cases[name] = common.fault_vector(case, f"cases.{name}")
            continue
        if not isinstance(case, Mapping) or not case:
            raise ValueError(
                f"cases.{name} must be a non-empty mapping {{kN: value}} or a list of {N_FAULTS} values, got {case!r}"
            )
        k = list(nominal)
        for key, value in case.items():
            m = _FAULT_KEY.match(str(key))
            if not m or not 1 <= int(m.group(1)) <= N_FAULTS:
                raise ValueError(f"cases.{name}: unknown fault {key!r}; use k1..k{N_FAULTS}")
            k[int(m.group(1)) - 1] = value
        cases[name] = common.fault_vector(k, f"cases.{name}")
    return cases


def run_cases(cfg: DictConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """Simulate nominal + cases in one batch, write CSVs, plots and ``metrics.json`` into ``cfg.out_dir``.

    Returns:
        ``metrics`` (the content of metrics.json) and ``objects`` (``signals``: the noise-free simulator
        output, batch order ``names``; ``out_dir``; ``params``; ``command``).
    """
    st = common.simulation_settings(cfg)
    params, fid, command, duration, seed, std, effects, dev = (
        st.params,
        st.fidelity,
        st.command,
        st.duration,
        st.seed,
        st.noise,
        st.effects,
        st.device,
    )
    nominal = common.fault_vector(list(params.nominal_faults), "actuator.nominal_faults")
    cases = parse_cases(cfg.get("cases"), nominal, cfg.get("only"))
    out_value = cfg.get("out_dir")
    if not isinstance(out_value, str) or not out_value.strip():
        raise ValueError(f"out_dir must be a directory path, got {out_value!r}")
    out_dir = Path(out_value).expanduser()

    names = ["nominal", *cases]
    faults = [nominal, *cases.values()]
    t0 = time.perf_counter()
    signals = EMASimulator(params, fid, effects=effects, device=dev).run(faults, command, duration)
    wall = time.perf_counter() - t0
    log.info("simulated %d actuators (%s, %.3g s) in %.1f s", len(names), fid, duration, wall)

    noisy = add_sensor_noise(signals.channels, std, seed)
    columns = [c for c in CSV_COLUMNS if c in noisy]
    stats = common.signal_metrics(signals.channels)
    clean = signals.channels
    results: dict[str, Any] = {}
    for i, name in enumerate(names):
        csv_path = write_measurement(out_dir / f"{name}.csv", {"time": signals.time, **noisy}, index=i, columns=columns)
        entry: dict[str, Any] = {"faults": faults[i]}
        if i > 0:
            for c in ("current", "position"):
                value = float(nrmse(clean[c][i], clean[c][0]))
                entry[f"nrmse_{c}"] = None if math.isnan(value) else value  # constant nominal: null
        entry.update({key: values[i] for key, values in stats.items()})
        entry["csv"] = csv_path.name
        if i > 0 and cfg.plot:
            from ..plotting import plot_signals  # matplotlib only when plotting

            runs = {
                "nominal": {c: noisy[c][0] for c in ("command", "position", "current")},
                name: {c: noisy[c][i] for c in ("command", "position", "current")},
            }
            plot = plot_signals(
                signals.time,
                runs,
                out_dir / f"{name}.png",
                title=f"{name} vs nominal ({fid.upper()}), faults={faults[i]}",
            )
            entry["plot"] = plot.name
        results[name] = entry

    metrics = {
        "fidelity": fid,
        "duration": duration,
        "samples": int(signals.time.numel()),
        "sample_rate": params.sample_rate,
        "seed": seed,
        "noise": std,
        "effects": sorted(common.plain(cfg.get("effects")) or {}),
        "nrmse_definition": "RMS(case - nominal) / (max(nominal) - min(nominal)), noise-free, fraction",
        "wall_time_s": round(wall, 3),
        "nominal": results["nominal"],
        "cases": {n: results[n] for n in names[1:]},
    }
    common.write_json(out_dir / "metrics.json", metrics)
    objects = {"signals": signals, "names": names, "out_dir": out_dir, "params": params, "command": command}
    return metrics, objects


@hydra.main(config_path=common.CONFIG_PATH, config_name="cases", version_base="1.3")
@common.report_errors("phm-cases")
def main(cfg: DictConfig) -> None:
    metrics, objects = run_cases(cfg)
    summary = {
        name: {"nrmse_current": c["nrmse_current"], "nrmse_position": c["nrmse_position"]}
        for name, c in metrics["cases"].items()
    }
    print(json.dumps(summary, indent=2), flush=True)
    print(f"results in {objects['out_dir']}", flush=True)


if __name__ == "__main__":
    main()
