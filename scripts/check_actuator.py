"""Design check of an actuator and its test command: loop margins, single-fault stability, HF-vs-LF agreement.

Usage:
    python scripts/check_actuator.py --actuator ema_hvdc_rudder --command chirp_hvdc_rudder
    python scripts/check_actuator.py --actuator path/to/my_actuator.yaml --command path/to/my_chirp.yaml \
        [--frequencies 3 5 8 ...] [--sweep-amplitude 5e-4] [--hf-cases nominal k3] [--no-hf] [--out report.json]

Prints a summary and writes the JSON report (phm_torch/assessment/actuator_check.py describes every figure).
Exit status 1 when a requirement fails (nominal margins below the requirements, or a single fault at k = 1
unstable). One torch thread; the HF runs take about a minute for 12 cases of a 0.75 s command.

Then what the health labels will see (phm_torch/assessment/label_check.py): the single faults assessed by phi_a with
the assessment config the data will be labelled with (``--assessment``, default the shipped
conf/assessment/frequency_response.yaml; ``--rotor-positions`` overrides its sweep's), a warning for each fault the
labels cannot see and the backlash level above which the play is wider than the labels' sweep.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import torch
from hydra.utils import instantiate

from phm_torch.assessment.actuator_check import ActuatorCheck, single_fault_cases
from phm_torch.assessment.label_check import absent_fault_message, label_visibility, load_assessment
from phm_torch.command import load_command_node
from phm_torch.io.atomic import atomic_open
from phm_torch.params import load_actuator
from phm_torch.provenance import actuator_record, command_record


def load_command(name: str) -> tuple[str, dict, object]:
    """(name, config node, command object) of ``conf/command/<name>.yaml`` or a YAML path."""
    label, node = load_command_node(name)
    return Path(label).stem, node, instantiate(node)


def _fmt(v: float, spec: str = ".1f", cap: float = math.inf) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "n/a"
    # a gain margin above 100 dB (cap): |L| ~ 0 at the phase crossover (e.g. a play wider than the sweep amplitude)
    return f">{cap:g}" if v > cap else format(v, spec)


def label_summary(labels: dict) -> str:
    sw = labels["sweep"]
    lines = [
        f"labels (phi_a): sweep {sw['frequencies'][0]:g}..{sw['frequencies'][-1]:g} Hz at {sw['amplitude']:.3g} rad, "
        f"{sw['rotor_positions']} rotor position(s); healthy at k = 1: "
        + ", ".join(n for n, c in labels["cases"].items() if c["healthy"] and n != "nominal")
    ]
    absent = labels.get("absent") or {}
    for name, value in absent.items():
        lines.append(f"WARNING: {absent_fault_message(name, value)}")
    for name in (n for n in labels["invisible"] if n not in absent):
        cause = (
            "the sweep keeps the rotor in one commutation sector; label with assessment.sweep.rotor_positions=3, "
            "the shipped value (check it here with --rotor-positions 3)"
            if sw["rotor_positions"] < 3
            else f"even at {sw['rotor_positions']} rotor positions: its effect is below what the sweep resolves"
        )
        lines.append(
            f"WARNING: {name} at k = 1 reads exactly the nominal margins: the health labels cannot see it ({cause})"
        )
    k2 = labels["k2_play_exceeds_sweep"]
    if k2 is not None:
        lines.append(
            f"note: above k2 = {k2:g} the play is wider than the labels' sweep amplitude: margins unmeasurable, "
            "labelled faulty (docs/own_actuator.md, the assessment check)"
        )
    return "\n".join(lines)


def summary(report: dict) -> str:
    lin, table = report["linear"]["nominal"], report["single_faults"]
    lines = [
        f"actuator {report['actuator']['name']}, command {report['command']['name']}",
        (
            f"linear loop: crossover {lin['crossover_hz']:.2f} Hz, PM {lin['phase_margin_deg']:.1f} deg, "
            f"GM {lin['gain_margin_db']:.2f} dB (phase crossover {lin['phase_crossover_hz']:.1f} Hz), "
            f"-3 dB bandwidth {lin['bandwidth_hz']:.1f} Hz"
        ),
        (
            f"LF sweep {report['sweep']['frequencies'][0]:g}..{report['sweep']['frequencies'][-1]:g} Hz at "
            f"{report['sweep']['amplitude']:.3g} rad; step {report['step']['amplitude']:.3g} rad, "
            f"{report['step']['duration']:g} s"
        ),
        (
            f"{'case':<12}{'fc Hz':>8}{'PM deg':>8}{'f180 Hz':>9}{'GM dB':>8}{'BW Hz':>8}"
            f"{'LF step':>9}{'HF step':>9}{'I nrmse':>9}{'pos nrmse':>10}  stable"
        ),
    ]
    for name, row in table.items():
        agr = report["agreement"].get(name, {})
        hf = {True: "ok", False: "FAIL", None: "-"}[row.get("hf_step_stable")]
        lines.append(
            f"{name:<12}{_fmt(row['crossover_hz']):>8}{_fmt(row['phase_margin_deg']):>8}"
            f"{_fmt(row['phase_crossover_hz']):>9}{_fmt(row['gain_margin_db'], '.2f', 100.0):>8}"
            f"{_fmt(row['bandwidth_hz']):>8}{'ok' if row['lf_step_stable'] else 'FAIL':>9}{hf:>9}"
            f"{_fmt(agr.get('current_nrmse', math.nan) * 100, '.2f') + '%' if agr else '-':>9}"
            f"{_fmt(agr.get('position_nrmse', math.nan) * 100, '.3f') + '%' if agr else '-':>10}"
            f"  {'yes' if row['stable'] else 'NO'}"
            + (
                "  (play > sweep amplitude: margins not meaningful, judged in time)"
                if not row["frequency_response_valid"]
                else ""
            )
        )
    v = report["verdict"]
    lines.append(
        "verdict: "
        + ", ".join(f"{k} {'ok' if ok else 'FAIL'}" for k, ok in v.items() if k != "pass")
        + f" -> {'PASS' if v['pass'] else 'FAIL'}  ({report['elapsed_s']} s)"
    )
    return "\n".join(lines)


# The envelope filter should remove at least this much at the Nyquist frequency (a factor 10 in amplitude).
ALIASING_LIMIT_DB = -20.0


def acquisition_summary(acq: dict) -> str:
    """One line on the sampling; a WARNING where the envelope filter lets the ripple alias into the records."""
    line = (
        f"acquisition: {acq['sample_rate_hz']:g} Hz, envelope filter {acq['filter_cutoff_hz']:g} Hz, "
        f"{acq['nyquist_attenuation_db']:.1f} dB at the Nyquist frequency"
    )
    if acq["nyquist_attenuation_db"] > ALIASING_LIMIT_DB:
        line += (
            f"\nWARNING: the envelope filter removes less than {-ALIASING_LIMIT_DB:g} dB at half the sample rate: "
            "the sampled current aliases the ripple above it (a phase-dependent error the model reproduces only "
            "where its PWM phase matches the bench's); lower filter_cutoff or raise sample_rate if the bench allows"
        )
    return line


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--actuator", required=True, help="conf/actuator/<name>.yaml name, or a YAML path")
    ap.add_argument("--command", required=True, help="conf/command/<name>.yaml name, or a YAML path")
    ap.add_argument("--frequencies", type=float, nargs="+", help="sweep grid [Hz] (default: from the linear loop)")
    ap.add_argument("--sweep-amplitude", type=float, help="sweep amplitude [rad] (default: from the actuator)")
    ap.add_argument("--hf-cases", nargs="*", help="cases simulated on HF too (default all; see --list-cases)")
    ap.add_argument("--no-hf", action="store_true", help="LF only (seconds)")
    ap.add_argument("--list-cases", action="store_true", help="print the single-fault case names and exit")
    ap.add_argument("--assessment", help="assessment config YAML (default the shipped conf/assessment)")
    ap.add_argument("--rotor-positions", type=int, help="the labels' sweep.rotor_positions (default: the config's)")
    ap.add_argument("--out", help="JSON report (default results/check_<actuator>_<command>.json)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    params = load_actuator(args.actuator)
    if args.list_cases:
        for name, k in single_fault_cases(params.nominal_faults).items():
            print(name, k)
        return 0
    cmd_name, node, command = load_command(args.command)
    act_name = Path(args.actuator).stem
    hf_cases = [] if args.no_hf else args.hf_cases
    check = ActuatorCheck(
        params,
        command,
        args.frequencies,
        args.sweep_amplitude,
        hf_cases=hf_cases,
        log=lambda msg: print(msg, file=sys.stderr, flush=True),
    )
    report = {"actuator": actuator_record(act_name, params), "command": command_record(cmd_name, node), **check.run()}
    report["acquisition"] = {
        "sample_rate_hz": params.sample_rate,
        "filter_cutoff_hz": params.filter_cutoff,
        "nyquist_attenuation_db": round(params.nyquist_attenuation_db, 2),
    }
    try:
        report["labels"] = label_visibility(params, *load_assessment(args.assessment, args.rotor_positions))
    except ValueError as err:  # e.g. an unstable nominal loop: no sweep to derive; the verdict above says why
        report["labels"] = {"error": str(err)}
    out = Path(args.out or f"results/check_{act_name}_{cmd_name}.json")
    with atomic_open(out) as fh:
        json.dump(report, fh, indent=2)
    print(summary(report))
    print(acquisition_summary(report["acquisition"]))
    error = report["labels"].get("error")
    print(f"labels (phi_a): not derived: {error}" if error else label_summary(report["labels"]))
    print(f"report: {out}")
    return 0 if report["verdict"]["pass"] else 1


if __name__ == "__main__":
    sys.exit(main())
