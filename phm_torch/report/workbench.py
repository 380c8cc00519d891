"""The workbench's HTML page (``report.html`` of ``phm-workbench``) from its ``report.json`` dict and its PNG
figures, built with the one report builder (:class:`~phm_torch.report.html.HtmlReport`).

The dict is :func:`phm_torch.workbench.report.report_dict`'s (its keys are documented there); this module
only lays it out, so it needs nothing of the workbench but that dict.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ..provenance import describe
from .html import HtmlReport, esc, table_html


def _pct(d: Mapping[str, Any] | None, key: str) -> str:
    return f"{100 * d[key]:.3f} %" if d and d.get(key) is not None else "–"


def html_page(report: dict, figs: dict[str, bytes]) -> str:
    """Self-contained HTML page of one workbench run (figures inline as base64 PNG)."""
    chans = report["channels"]
    r = HtmlReport("phm_torch workbench report", heading="Model vs measurement")

    def img(name: str) -> None:
        if name in figs:
            r.figure(figs[name], alt=name)

    files = ", ".join(f"{f['path']} (sha256 {str(f['sha256'])[:8]})" for f in report["measurement_files"]) or ", ".join(
        report["measurements"]
    )
    r.paragraph(
        f"Actuator: {describe(report['actuator'])}; measurements: {files}; model fidelity "
        f"{report['fidelity'].upper()}; channels {', '.join(chans)}."
    )
    best = next((c for c in report["candidates"] if c["significant"]), None)
    summary = (
        f"Calibrated model NRMSE {_pct(report['nrmse'], 'total')} against a noise floor of "
        f"{_pct(report['noise_floor'], 'total')}. "
    )
    if best:
        summary += (
            f"Most likely missing effect: <b>{esc(best['label'])}</b> (p = {best['p_value']:.3g}; "
            f"{esc(best['evidence'].get('summary', ''))}); with it the NRMSE falls to "
            f"{_pct(best, 'nrmse_after_refit')}."
        )
    else:
        summary += "No library effect explains the residual beyond noise."
    gap = report.get("fidelity_gap")
    if gap and gap["above_floor"]:
        summary += (
            f" <b>On these records' commands the LF model itself differs from the HF model by "
            f"{_pct(gap['nrmse'], 'total')}</b>, above the noise floor (most at "
            f"{', '.join(f'{t:g} s' for t in gap['worst_t'])}): an effect smaller than that can be hidden by the LF "
            f"model's own error; {esc(gap.get('advice', 'run the workbench with fidelity=hf'))}."
        )
    for name, found in (report.get("bench_lines") or {}).items():
        lines = ", ".join(f"{x['frequency']:.5g} Hz ({100.0 * x['share']:.3g} % of the RMS current)" for x in found)
        summary += (
            f" <b>The measured current of {esc(name)} carries a line through the whole record at {lines}</b> that the "
            "model does not make: a bench's hum, not an effect of the actuator; it was removed before calibrating."
        )
    r.markup(f"<p>{summary}</p>")
    orders = ", ".join(f"{k} {v}" for k, v in report["orders"].get("actuator", {}).items())
    residual = ", ".join(map(str, report["orders"].get("residual", []))) or "–"
    r.paragraph(
        f"Rotor-angle orders: the actuator's {orders}; the residual's strongest {residual} (analysed up "
        f"to {report['orders'].get('max_order', '–')})."
    )

    r.section("Add it and watch the error fall")
    r.table(
        ["model", *[f"NRMSE {c}" for c in chans], "NRMSE total", "white residual", "BIC", "fitted"],
        [
            [
                b["model"],
                *[_pct(b["nrmse"], c) for c in chans],
                _pct(b["nrmse"], "total"),
                b["white"],
                b["bic"],
                "; ".join(f"{k} = {v[0]:.4g} ± {v[1]:.2g}" for k, v in b["fitted"].items() if v[0] is not None),
            ]
            for b in report["before_after"]
        ],
    )
    img("before_after.png")
    if report.get("retrain"):
        r.markup(
            f"<p>Train the surrogates on this physics: <code>phm-generate {esc(report['retrain'])}</code>, "
            "then <code>phm-train</code> on that store (docs/surrogates.md, modelling differences).</p>"
        )

    r.section("Compare", "Calibrated model (configured effects) against the measurement.")
    r.table(
        ["channel", "NRMSE", "fit %", "noise floor (NRMSE of a perfect model)", "noise std"],
        [
            [
                c,
                _pct(report["nrmse"], c),
                report["fit_percent"][c],
                _pct(report["noise_floor"], c),
                report["noise_std"][c],
            ]
            for c in chans
        ],
    )
    img("overlay.png")

    r.section("Where it fails")
    r.section("Worst windows", level=3)
    r.table(
        ["record", "t start [s]", "t end [s]", "NRMSE"],
        [[w["record"], w["t_start"], w["t_end"], _pct(w, "nrmse")] for w in report["worst_windows"]],
    )
    r.section("Residual maps", level=3)
    img("residual_maps.png")
    r.section("Harmonic content (rotor angle)", level=3)
    r.table(
        ["channel", "top mechanical harmonics (order: amplitude r/σ)"],
        [[c, ", ".join(f"{h['order']}: {h['amplitude']:.3g}" for h in hs)] for c, hs in report["harmonics"].items()],
    )
    img("harmonics.png")
    r.section("Residual spectrum", level=3)
    img("spectrum.png")
    r.section("Residual tests", level=3)
    tests = report["tests"]
    r.table(
        ["channel", "whiteness p (Ljung-Box)", "white", "residual–command p", "uncorrelated"],
        [
            [
                c,
                tests["whiteness"][c]["p_value"],
                tests["whiteness"][c]["white"],
                tests["cross_correlation"][c]["p_value"],
                tests["cross_correlation"][c]["uncorrelated"],
            ]
            for c in chans
        ],
    )
    img("correlations.png")

    r.section(
        "Which effect is missing",
        f"Score test per library effect; the top candidates refitted. Significant: "
        f"p below {report['significance_level']:.3g} (Bonferroni), explains at least "
        f"{100 * report['min_gain']:g} % of the residual sum of squares, and (refitted) lowers the BIC.",
    )
    r.table(
        [
            "effect",
            "score T",
            "dof",
            "p-value",
            "residual explained",
            "significant",
            "NRMSE after refit",
            "ΔBIC",
            "evidence",
            "physics",
        ],
        [
            [
                c["label"],
                c["score"],
                c["dof"],
                c["p_value"],
                _pct(c, "explained_fraction"),
                c["significant"],
                _pct(c, "nrmse_after_refit"),
                c["delta_bic"],
                c["evidence"].get("summary") if c["evidence"] else None,
                c["evidence"].get("explains") if c["evidence"] else None,
            ]
            for c in report["candidates"]
        ],
    )
    img("candidates.png")

    if report["closure"]:
        cl = report["closure"]
        verdict = (
            f"It depends mostly on <b>{esc(cl['lead'])}</b>: the lead for writing the missing effect."
            if cl["explains"]
            else "It does not explain the residual either: what is missing is not a simple "
            "function of the state (e.g. a structural difference of the model)."
        )
        inputs = ", ".join(map(str, cl["harmonics"]))
        r.section("Neural closure")
        r.markup(
            f"<p>No library effect explained the residual; a small network of the rotor-angle orders "
            f"{esc(inputs)}, speed, current and surface angle, added to the {esc(cl['equation'])} equation, "
            f"explains {100 * cl['explained_fraction']:.1f} % of the residual sum of squares (NRMSE "
            f"{_pct(cl['nrmse'], 'total')}). {verdict}</p>"
            + table_html(["input", "share"], [[k, f"{100 * v:.1f} %"] for k, v in cl["inputs"].items()])
        )
        img("closure.png")

    r.section("Calibrated parameters (configured model)")
    r.table(["parameter", "value", "std"], [[k, v[0], v[1]] for k, v in report["fitted"].items()])
    r.note("Timing [s]: " + ", ".join(f"{k} {v:.1f}" for k, v in report["timing"].items()))
    return r.render()
