"""``phm-fit-lf``: fit an actuator's LF shape coefficients to its HF model on a test command.

Examples::

    phm-fit-lf                                               # ema_reference on the chirp
    phm-fit-lf actuator=my_ema command=sine out=my_conf/actuator/my_ema_lf.yaml
    phm-fit-lf fit.n_design=8 fit.n_importance=8 fit.n_uniform=8 fit.max_iter=3

Writes ``out``: the input actuator's values with the ``lf_shape`` block replaced by the coefficients
kept (fitted, or the physical values when the fit does not improve the held-out discrepancy; the rule is
in :mod:`phm_torch.lf_fit`), usable as ``conf/actuator/<name>.yaml``; beside it ``<stem>.report.json``
(coefficients, decision and its reasons, NRMSE before/after on every set) and ``<stem>.report.png``.
Both files carry the provenance of the actuator and command they were fitted for. The work is done by
:func:`fit_lf` (a plain function of the composed config); :func:`main` is the thin Hydra entry point.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path
from typing import Any

import hydra
import yaml
from omegaconf import DictConfig

from .. import lf_fit, provenance
from ..io.atomic import atomic_open
from . import common

log = logging.getLogger(__name__)
LONG_FIT_PERIODS = 20_000  # control periods per simulated vector above which the fit says how to shorten it


def output_path(value: Any, default_name: str) -> Path:
    """The actuator YAML path: ``out`` as given, or ``default_name`` in the Hydra run directory (the working
    directory outside Hydra)."""
    if value is None:
        return (common.hydra_output_dir() or Path.cwd()) / default_name
    if not isinstance(value, str) or not value.strip():
        raise ValueError(f"out must be a file path ending in .yaml, got {value!r}")
    path = Path(value).expanduser()
    if path.suffix.lower() not in (".yaml", ".yml"):
        raise ValueError(f"out must end in .yaml (an actuator config; the report goes beside it), got {value!r}")
    return path


def actuator_yaml(values: dict[str, Any], shape: lf_fit.LFShape, header: list[str]) -> str:
    """The actuator YAML: ``values`` (the input actuator's fields, in their order) with ``lf_shape``
    replaced, after ``header`` comment lines (comments, so ``ActuatorParams.from_mapping`` reads the file
    as any actuator config)."""
    data = {k: v for k, v in values.items() if k != "lf_shape"}
    data["lf_shape"] = dataclasses.asdict(shape)
    body = yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=120)
    return "".join(f"# {line}\n" for line in header) + body


def plot_report(result: lf_fit.LFFitResult, path: Path, title: str) -> Path:
    """Held-out NRMSE per vector, fitted against physical coefficients (one panel per channel), as PNG."""
    from matplotlib.ticker import NullFormatter

    from ..plotting import plt  # matplotlib (Agg) only when plotting

    fig, axes = plt.subplots(1, len(lf_fit.CHANNELS), figsize=(8, 3.6))
    for ax, (i, channel) in zip(axes, enumerate(lf_fit.CHANNELS)):
        lo, hi = float("inf"), 0.0
        for name in lf_fit.HELD_OUT:
            x = [100 * d[i] for d in result.per_vector[name]["physical"]]
            y = [100 * d[i] for d in result.per_vector[name]["fitted"]]
            ax.scatter(x, y, s=12, label=name)
            lo, hi = min(lo, *x, *y), max(hi, *x, *y)
        lo = max(lo, 1e-4)
        ax.plot([lo, hi], [lo, hi], "k:", lw=0.8)
        ax.set(
            xscale="log", yscale="log", xlabel=f"{channel} NRMSE, physical [%]", ylabel=f"{channel} NRMSE, fitted [%]"
        )
        for axis in (ax.xaxis, ax.yaxis):  # decade labels only: minor labels of a short log range overlap
            axis.set_minor_formatter(NullFormatter())
        ax.legend(fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    with atomic_open(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=100)
    plt.close(fig)
    return path


def fit_lf(cfg: DictConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """Fit, validate and decide, then write the actuator YAML, the JSON report and the PNG.

    Every input is validated before the first simulation; errors are ValueErrors naming the field.

    Returns:
        ``metrics``: the coefficients kept and which (``kept``: ``fitted`` | ``physical``) with the reasons,
        the fitted coefficients, held-out median/max NRMSE of current and position with the physical and
        the fitted coefficients and with the physical ones + ``lf_fit.JITTER`` (the noise floor of the
        comparison), fractions; wall time, output paths; ``objects``: ``result``
        (:class:`~phm_torch.lf_fit.LFFitResult`), ``params``, ``yaml``, ``report``, ``plot`` paths.
    """
    common.set_threads(cfg)
    params = common.actuator(cfg)
    command = common.command(cfg.command)
    settings: lf_fit.LFFitSettings = common.build(cfg.fit, "fit")
    duration = settings.duration if settings.duration is not None else getattr(command, "duration", None)
    common.number(duration, "fit.duration", 0.0, strict=True)
    records = common.requested_provenance(cfg)
    yaml_path = output_path(cfg.get("out"), f"{records['actuator']['name']}_lf.yaml")
    stem = yaml_path.with_suffix("")
    report_path, plot_path = Path(f"{stem}.report.json"), Path(f"{stem}.report.png")

    periods = duration * float(params.pwm_frequency)
    if periods > LONG_FIT_PERIODS:
        log.warning(
            "phm-fit-lf: %.0f control periods per simulated vector (%g s at %g Hz PWM); the fit's cost grows with "
            "them (48,000 took 14 min on one thread, 7,500 take 2 min): fit.duration=<s> fits on the first part of "
            "the command",
            periods,
            duration,
            float(params.pwm_frequency),
        )
    t0 = time.perf_counter()
    result = lf_fit.run_fit(params, command, settings)
    wall = time.perf_counter() - t0

    held = {
        name: {label: result.summary[name][label] for label in ("physical", "fitted", "jitter")}
        for name in lf_fit.HELD_OUT
    }
    kept = dataclasses.asdict(result.shape)
    header = [
        (
            f"phm-fit-lf: actuator {provenance.describe(records['actuator'])} with lf_shape fitted to HF on "
            f"command {provenance.describe(records['command'])}"
        ),
        f"kept: {result.decision.keep} coefficients ({'; '.join(result.decision.reasons)})",
        f"report: {report_path.name}",
        "provenance (of the input actuator and the command): " + json.dumps(records),
    ]
    with atomic_open(yaml_path, "w") as fh:
        fh.write(actuator_yaml(common.plain(cfg.actuator), result.shape, header))
    report = {
        "provenance": records,
        "kept": result.decision.keep,
        "reasons": result.decision.reasons,
        "lf_shape": kept,
        "fitted": dataclasses.asdict(result.fit.shape),
        "physical": dataclasses.asdict(lf_fit.LFShape()),
        "input": dataclasses.asdict(params.lf_shape),
        # no Gauss-Newton std: the cost jitters at the scale of the jitter candidate, not a smooth bowl
        "fit": {
            "cost_history": result.fit.cost_history,
            "iterations": result.fit.iterations,
            "converged": result.fit.converged,
            "at_bound": result.fit.at_bound,
            "excluded_design_rows": result.fit.excluded,
        },
        "settings": dataclasses.asdict(settings),
        "duration": duration,
        "wall_time_s": round(wall, 1),
        "nrmse": result.summary,
        "per_vector": result.per_vector,
        "actuator_yaml": str(yaml_path),
    }
    common.write_json(report_path, report)
    if cfg.plot:
        plot_report(
            result,
            plot_path,
            f"{records['actuator']['name']} on {records['command']['name']}: kept {result.decision.keep}",
        )
    else:
        plot_path = None

    metrics = {
        "kept": result.decision.keep,
        "reasons": result.decision.reasons,
        "lf_shape": kept,
        "fitted": report["fitted"],
        "held_out": held,
        "wall_time_s": round(wall, 1),
        "actuator_yaml": str(yaml_path),
        "report": str(report_path),
        "plot": str(plot_path) if plot_path else None,
    }
    objects = {"result": result, "params": params, "yaml": yaml_path, "report": report_path, "plot": plot_path}
    return metrics, objects


@hydra.main(config_path=common.CONFIG_PATH, config_name="fit_lf", version_base="1.3")
@common.report_errors("phm-fit-lf")
def main(cfg: DictConfig) -> None:
    metrics, _ = fit_lf(cfg)
    log.info("wrote %s and %s", metrics["actuator_yaml"], metrics["report"])
    print(json.dumps(metrics, indent=2), flush=True)


if __name__ == "__main__":
    main()
