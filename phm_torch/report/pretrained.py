"""The report section "Pretrained pipeline on the bundled records": what the shipped paper-scale pipeline
(``pretrained/``) says about the example records that ship with the repository (``examples/``) and the run's
virtual-bench records, beside the run's own small-data figures.

The study dict (written by ``phm-run``'s report stage, :func:`phm_torch.apps.run.pretrained_study`)::

    {"pipeline": str, "actuator": str, "command": str,      # the pipeline file and its provenance, described
     "skipped": str | None,                                 # why it was not run (another actuator, no file)
     "notes": [str],                                        # records left out and why
     "records": [{"name": str, "source": str,               # file name, what the record is
                  "true_k": {fault: value} | None,          # the injected faults differing from nominal
                  "prediction": {...}}]}                    # phm-predict's record (k_hat, healthy, p_faulty,
                                                            # rul_hours, out_of_distribution, noise, ...)
"""

from __future__ import annotations

from typing import Any

from .html import HtmlReport

TITLE = "Pretrained pipeline on the bundled records (paper scale)"


def _rul(pred: dict[str, Any], q: str) -> str | float | None:
    """One RUL quantile [h]: a bound past the damage model's horizon is censored (unknown, not a number)."""
    if pred.get("out_of_distribution") or pred.get("rul_hours") is None:
        return None
    value = pred["rul_hours"].get(q)
    return "> horizon" if value is None else value


def _pct(v: float | None) -> float | None:
    return None if v is None else 100 * v


def pretrained_section(r: HtmlReport, study: dict[str, Any] | None) -> None:
    """Append the section to ``r`` (a line saying why when ``study`` is missing or was skipped)."""
    r.section(TITLE)
    if not study:
        r.note("(not run: this run's report stage had no pretrained pipeline configured, report.pretrained=null)")
        return
    r.paragraph(
        f"The shipped pipeline {study['pipeline']} (the best configuration trained on 80,000 HF signals; "
        f"pretrained/README.md) for {study.get('actuator')} on {study.get('command')}, run by phm-predict "
        "on the records that ship with the repository and on this run's virtual bench. Unlike the run's own "
        "pipeline above, it is at paper scale: its verdicts and k_hat are what the method gives."
    )
    if study.get("skipped"):
        r.note(f"(not run: {study['skipped']})")
        return
    records = study.get("records") or []
    rows = []
    for rec in records:
        pred, true = rec["prediction"], rec.get("true_k")
        k_hat = pred.get("k_hat") or {}
        injected = (
            "; ".join(f"{k} {v:g} (k_hat {k_hat.get(k, float('nan')):.3f})" for k, v in true.items())
            if true
            else "none"
        )
        rows.append(
            [
                rec["name"],
                rec["source"],
                injected,
                "faulty" if not pred.get("healthy") else "healthy",
                _pct(pred.get("p_faulty")),
                _rul(pred, "p5"),
                _rul(pred, "p50"),
                _rul(pred, "p95"),
                _pct(pred.get("noise")),
                "no" if pred.get("out_of_distribution") else "yes",
            ]
        )
    r.table(
        [
            "record",
            "what it is",
            "faults injected (k_hat of each)",
            "verdict",
            "P(faulty) [%]",
            "RUL p5 [h]",
            "RUL p50 [h]",
            "RUL p95 [h]",
            "noise [% of RMS]",
            "in distribution",
        ],
        rows,
    )
    if records:
        names = list((records[0]["prediction"].get("k_hat") or {}).keys())
        r.table(
            ["k_hat", *names],
            [[rec["name"], *[(rec["prediction"].get("k_hat") or {}).get(n) for n in names]] for rec in records],
            digits=3,
        )
    notes = [
        (
            "RUL '> horizon': a bound beyond the damage model's horizon (censored, unknown); a dash: no RUL, the "
            "record is out of distribution."
        ),
        (
            "A fault injected is not a failed actuator: the verdict says whether the actuator still meets its "
            "performance requirements (the assessment function), so a small fault can read healthy."
        ),
        (
            "No bench baseline is given: each record is read as a record of the training model (phm-predict "
            "baseline=, docs/surrogates.md 'Modelling differences')."
        ),
    ]
    if any(rec["prediction"].get("noise_above_calibration") for rec in records):
        notes.append(
            "A record with noise above twice the calibration noise has too narrow P(faulty), intervals "
            "and RUL band: read those with care."
        )
    not_identified = sorted({n for rec in records for n in rec["prediction"].get("k_not_identified") or []})
    if not_identified:
        notes.append(
            f"Not identified by the test command (their k_hat is mostly the training prior): "
            f"{', '.join(not_identified)}."
        )
    for text in [*notes, *(study.get("notes") or [])]:
        r.note(text)
