"""``phm-simulate``: simulate one actuator on one command; write a measurement CSV and a PNG beside it.

Examples::

    phm-simulate                                              # HF, nominal, paper chirp
    phm-simulate fidelity=lf 'faults=[0.5,0,0,0,0,0,0.5,0.5]' out=friction.csv
    phm-simulate seed=3 noise.current=0.02 noise.position=1e-5 out=noisy.csv
    phm-simulate +effects.cogging_torque.amplitude=0.003 command.duration=0.2

The work is done by :func:`simulate_to_csv` (a plain function of the composed config, usable from
Python and tests); :func:`main` is the thin Hydra entry point.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from ..io import write_measurement
from ..sensor_noise import add_sensor_noise
from ..simulator import EMASimulator
from . import common

log = logging.getLogger(__name__)

CSV_COLUMNS = ("speed", "motor_angle", "ia", "ib", "ic")  # written after time, command, position, current


def output_path(value: Any, default_name: str) -> Path:
    """The CSV path: ``out`` as given (relative to the working directory), or ``default_name`` in the Hydra
    run directory (the working directory outside Hydra)."""
    if value is None:
        return (common.hydra_output_dir() or Path.cwd()) / default_name
    if not isinstance(value, str) or not value.strip():
        raise ValueError(f"out must be a file path ending in .csv, got {value!r}")
    path = Path(value).expanduser()
    if path.suffix.lower() != ".csv":
        raise ValueError(f"out must end in .csv (the plot goes beside it as .png), got {value!r}")
    return path


def simulate_to_csv(cfg: DictConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """Simulate the configured actuator and write the CSV (and the plot).

    Every input is validated before the simulation starts; errors are ValueErrors naming the field.

    Returns:
        ``metrics``: tracking error RMS/max [rad], peak current [A], peak motor speed [rad/s] of the
        noise-free simulation, plus run information; ``objects``: ``signals`` (the simulator output,
        noise-free), ``channels`` (what was written, noise included), ``params``, ``command``,
        ``csv`` and ``plot`` paths.
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
    faults = common.fault_vector(cfg.faults)
    csv_path = output_path(cfg.get("out"), "simulation.csv")

    t0 = time.perf_counter()
    sim = EMASimulator(params, fid, effects=effects, device=dev)
    signals = sim.run(faults, command, duration)
    wall = time.perf_counter() - t0

    channels = add_sensor_noise(signals.channels, std, seed)
    columns = [c for c in CSV_COLUMNS if c in channels]
    write_measurement(csv_path, {"time": signals.time, **channels}, index=0, columns=columns)
    plot_path = None
    if cfg.plot:
        from ..plotting import plot_signals  # matplotlib only when plotting

        plot_path = plot_signals(
            signals.time,
            {"simulation": {k: channels[k][0] for k in ("command", "position", "current")}},
            csv_path.with_suffix(".png"),
            title=f"{fid.upper()} simulation, faults={faults}",
        )

    stats = common.signal_metrics(signals.channels)
    metrics = {key: values[0] for key, values in stats.items()}
    metrics.update(
        fidelity=fid,
        faults=faults,
        duration=duration,
        samples=int(signals.time.numel()),
        seed=seed,
        noise=std,
        effects=sorted(common.plain(cfg.get("effects")) or {}),
        wall_time_s=round(wall, 3),
        csv=str(csv_path),
        plot=str(plot_path) if plot_path else None,
    )
    objects = {
        "signals": signals,
        "channels": channels,
        "params": params,
        "command": command,
        "csv": csv_path,
        "plot": plot_path,
    }
    return metrics, objects


@hydra.main(config_path=common.CONFIG_PATH, config_name="simulate", version_base="1.3")
@common.report_errors("phm-simulate")
def main(cfg: DictConfig) -> None:
    metrics, _ = simulate_to_csv(cfg)
    log.info("wrote %s", metrics["csv"])
    print(json.dumps(metrics, indent=2), flush=True)


if __name__ == "__main__":
    main()
