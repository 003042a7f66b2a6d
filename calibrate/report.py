"""Self-contained HTML commissioning report (``RUN_DIR/report.html``).

One file, no network: plots are matplotlib (Agg) PNGs embedded as base64 ``data:`` URIs, the
style is inline. Sections, in order: verdict and failed checks, the acceptance checks, the
held-out metrics in the paper's table columns, the leak-test pressure trace, camera health maps,
the per-pixel no-contact maps (valid-depth count, error mean, error variance; the paper's Fig. 5),
held-out examples IR / measured / predicted / error (Fig. 6), the training curve, the model
compared with the ToF against the true depth (simulated runs), the pose check, and the run
details. A section whose data the run did not produce (e.g. a sensor rejected at the leak test
has no model) says so.
"""

from __future__ import annotations

import base64
import html
import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calibrate.acceptance import NOT_RUN, check_limits, check_value_text, limit_text, reads_on_the_same_side
from collect.atomic_files import write_text
from collect.errors import HOST_FAULTS

#: The paper's table columns: (metric key, header, format).
PAPER_COLUMNS = (
    ("abs_rel", "Abs.Rel", "{:.4f}"),
    ("sq_rel", "Sq.Rel (m)", "{:.2e}"),  # a length, as DESIGN.md defines it (was: no unit beside RMSE in mm)
    ("rmse", "RMSE (mm)", "mm"),
    ("rmse_log", "RMSE_log", "{:.4f}"),
    ("silog", "SILog", "{:.3f}"),
    ("a1", "&delta;&lt;1.05", "{:.3f}"),
    ("a2", "&delta;&lt;1.05<sup>2</sup>", "{:.3f}"),
    ("a3", "&delta;&lt;1.05<sup>3</sup>", "{:.3f}"),
)


@dataclass
class ReportData:
    """Everything the report shows. Arrays: depth in m, images ``(H,W)`` or ``(K,H,W)``."""

    serial: str
    accepted: bool
    checks: list[dict]
    simulated: bool
    reason: str = ""  # one line why rejected
    fault: str | None = None
    stopped: bool = False
    run_info: dict = field(default_factory=dict)  # shown as a key/value table
    heldout_metrics: dict | None = None  # METRIC_KEYS -> value
    contact_metrics: dict | None = None  # the same on the held-out contact patches only
    leak_t: np.ndarray | None = None  # (P,) s
    leak_hpa: np.ndarray | None = None  # (P,) hPa
    camera_ir_mean: np.ndarray | None = None  # (H,W) float32
    camera_dead_mask: np.ndarray | None = None  # (H,W) bool
    camera_stuck_mask: np.ndarray | None = None  # (H,W) bool
    camera_dot_mask: np.ndarray | None = None  # (H,W) bool
    nocontact_valid_count: np.ndarray | None = None  # (H,W) int frames with valid ToF depth
    nocontact_err_mean: np.ndarray | None = None  # (H,W) m, predicted - measured
    nocontact_err_var: np.ndarray | None = None  # (H,W) m^2
    example_ir: np.ndarray | None = None  # (K,H,W) amplitude
    example_depth: np.ndarray | None = None  # (K,H,W) m ToF, 0 = invalid
    example_pred: np.ndarray | None = None  # (K,H,W) m
    example_true: np.ndarray | None = None  # (K,H,W) m, simulated runs
    example_labels: list[str] = field(default_factory=list)
    training_curve: list[dict] = field(default_factory=list)  # {step, elapsed_s, loss (m) | None, a1 | None}
    truth_comparison: dict | None = None  # {"model", "tof", "model_all" (optional): metrics, "dropouts": {...}}
    pose: dict | None = None  # pose check results
    notes: dict[str, str] = field(default_factory=dict)  # section -> why it is missing


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _img(uri: str, alt: str) -> str:
    return f'<img src="{uri}" alt="{html.escape(alt)}">'


#: The checks judged on a metrics row's cells: metric key -> check name (the check's value is the
#: cell's, in the cell's unit), for the held-out row, its contact-patch row and the row against the truth.
HELDOUT_CELL_CHECKS = {"a1": "heldout_a1", "abs_rel": "heldout_abs_rel", "rmse": "heldout_rmse_mm"}
CONTACT_CELL_CHECKS = {"rmse": "contact_rmse_mm"}
TRUTH_CELL_CHECKS = {"a1": "truth_a1"}


def cell_checks(checks: list[dict], names: dict[str, str]) -> dict[str, dict]:
    """Metric key -> the check of ``checks`` named for it in ``names`` (those made)."""
    by_name = {c["name"]: c for c in checks}
    return {key: by_name[name] for key, name in names.items() if name in by_name}


def _fmt_metric(fmt: str, value, check: dict | None = None) -> str:
    """A metrics table cell; where ``check`` judged it and the table's rounding would put it on the
    other side of the check's limit, the check's own text (was: a failed a1 of 0.94996 read 0.950
    beside a minimum of 0.95)."""
    if value is None or not np.isfinite(value):
        return "&ndash;"
    text = f"{value * 1000:.3f}" if fmt == "mm" else fmt.format(value)
    if (check is not None and check["value"] is not None
            and not reads_on_the_same_side(float(text), check["value"], check_limits(check))):
        return check_value_text(check)
    return text


def metrics_table(rows: list[tuple[str, dict, dict[str, dict]]]) -> str:
    """HTML table of ``(label, metrics, cell_checks)`` rows in the paper's columns (``cell_checks``:
    metric key -> the acceptance check judged on that cell, ``cell_checks``)."""
    head = "".join(f"<th>{h}</th>" for _, h, _ in PAPER_COLUMNS)
    body = ""
    for label, m, judged in rows:
        cells = "".join(f"<td>{_fmt_metric(f, m.get(k), judged.get(k))}</td>" for k, _, f in PAPER_COLUMNS)
        body += f"<tr><th>{html.escape(label)}</th>{cells}</tr>"
    return f"<table class='metrics'><tr><th></th>{head}</tr>{body}</table>"


def _checks_table(checks: list[dict]) -> str:
    rows = ""
    for c in checks:
        thr = c["threshold"]
        thr_s = (f"{limit_text(thr[0])} &ndash; {limit_text(thr[1])}" if isinstance(thr, (list, tuple))
                 else html.escape(f"{c['op']} {limit_text(thr)}"))
        val = "&ndash;" if c["value"] is None else check_value_text(c)
        cls = "pass" if c["passed"] else ("fail" if c["verdict"] == "fail" else "skip")  # skip: not run
        rows += (
            f"<tr class='{cls}'><td>{html.escape(c['name'])}</td><td>{val}</td><td>{thr_s}</td>"
            f"<td>{html.escape(c.get('unit', ''))}</td><td class='v'>{c['verdict'].upper()}</td>"
            f"<td>{html.escape(c['reason'])}</td></tr>"
        )
    return (
        "<table class='checks'><tr><th>check</th><th>value</th><th>threshold</th><th>unit</th>"
        f"<th>verdict</th><th>reason</th></tr>{rows}</table>"
    )


def _leak_plot(t, hpa) -> str:
    """The hold's pressure trace (``t (P,) s``, ``hpa (P,) hPa``) and the line the leak check judged."""
    import matplotlib.pyplot as plt

    from calibrate.leak_test import analyse_leak

    leak = analyse_leak(t, hpa)
    fig, ax = plt.subplots(figsize=(6, 2.6))
    ax.plot(leak.t, leak.hpa, ".", ms=2, color="tab:blue", label="pressure")
    ax.plot(leak.t, leak.fitted_hpa(), color="tab:red", label=f"fit: {leak.rate_hpa_per_min:.3f} hPa/min loss")
    ax.set_xlabel("hold time (s)")
    ax.set_ylabel("pressure (hPa abs)")
    ax.ticklabel_format(axis="y", useOffset=False)
    ax.legend(loc="best", fontsize=8)
    ax.grid(alpha=0.3)
    return _png(fig)


def _map_row(maps: list[tuple[str, np.ndarray, str]], figsize=(10, 2.8)) -> str:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(maps), figsize=figsize)
    for ax, (title, image, cmap) in zip(np.atleast_1d(axes), maps):
        finite = image[np.isfinite(image)] if np.issubdtype(image.dtype, np.floating) else image.ravel()
        vmin, vmax = (np.percentile(finite, [1, 99]) if finite.size else (0, 1))
        if cmap == "coolwarm":
            lim = max(abs(vmin), abs(vmax), 1e-12)
            vmin, vmax = -lim, lim
        im = ax.imshow(image, cmap=cmap, vmin=vmin, vmax=vmax if vmax > vmin else vmin + 1)
        ax.set_title(title, fontsize=9)
        ax.axis("off")
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03)
    fig.tight_layout()
    return _png(fig)


def _camera_plot(ir_mean, dead, stuck, dots) -> str:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(8, 3))
    axes[0].imshow(ir_mean, cmap="gray")
    ys, xs = np.nonzero(dead)
    axes[0].plot(xs, ys, "s", ms=3, mfc="none", mec="red", label=f"dead ({dead.sum()})")
    ys, xs = np.nonzero(stuck)
    axes[0].plot(xs, ys, "s", ms=3, mfc="none", mec="orange", label=f"stuck ({stuck.sum()})")
    axes[0].legend(loc="lower right", fontsize=7)
    axes[0].set_title("mean IR, defective pixels", fontsize=9)
    axes[1].imshow(dots, cmap="gray_r")
    axes[1].set_title("detected dot pattern", fontsize=9)
    for ax in axes:
        ax.axis("off")
    fig.tight_layout()
    return _png(fig)


def _examples_plot(ir, depth, pred, labels, true=None) -> str:
    """Grid: one row per frame; IR, measured depth, predicted depth, |pred - measured| (+ true)."""
    import matplotlib.pyplot as plt

    k = ir.shape[0]
    cols = 5 if true is not None else 4
    fig, axes = plt.subplots(k, cols, figsize=(2.6 * cols, 2.1 * k), squeeze=False)
    valid_all = depth[depth > 0]
    lo, hi = (np.percentile(valid_all, [1, 99]) if valid_all.size else (pred.min(), pred.max()))
    for i in range(k):
        d = np.where(depth[i] > 0, depth[i], np.nan)
        err = np.where(depth[i] > 0, np.abs(pred[i] - depth[i]) * 1000, np.nan)
        panels = [
            ("IR", ir[i], "gray", None, None),
            ("measured depth (m)", d, "viridis", lo, hi),
            ("predicted depth (m)", pred[i], "viridis", lo, hi),
            ("|error| (mm)", err, "magma", 0, max(np.nanpercentile(err, 99) if np.isfinite(err).any() else 1, 1e-3)),
        ]
        if true is not None:
            panels.append(("true depth (m)", true[i], "viridis", lo, hi))
        for j, (title, image, cmap, vmin, vmax) in enumerate(panels):
            ax = axes[i, j]
            im = ax.imshow(image, cmap=cmap, vmin=vmin, vmax=vmax)
            # an object's name is text: a mesh cup$^$.stl was read as math, and the report failed before registration
            ax.set_title(f"{title}" + (f"\n{labels[i]}" if j == 0 and i < len(labels) else ""), fontsize=8,
                         parse_math=False)
            ax.axis("off")
            if j > 0:
                fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03)
    fig.tight_layout()
    return _png(fig)


def _truth_plot(true, tof, pred) -> str:
    """One frame: true depth, ToF with its dropouts, model, and both errors against the truth (mm)."""
    import matplotlib.pyplot as plt

    membrane = true > 0
    dropout = membrane & (tof <= 0)
    tof_err = np.where(membrane & ~dropout, np.abs(tof - true) * 1000, np.nan)
    model_err = np.where(membrane, np.abs(pred - true) * 1000, np.nan)
    finite = np.concatenate([tof_err[np.isfinite(tof_err)], model_err[np.isfinite(model_err)]])
    emax = max(float(np.percentile(finite, 99)) if finite.size else 1.0, 1e-3)
    lo, hi = np.percentile(true[membrane], [1, 99]) if membrane.any() else (0, 1)
    fig, axes = plt.subplots(1, 5, figsize=(14, 2.6))
    panels = [
        ("true depth (m)", np.where(membrane, true, np.nan), "viridis", lo, hi),
        (f"ToF (red: {dropout.sum()} dropouts)", np.where(tof > 0, tof, np.nan), "viridis", lo, hi),
        ("model (m)", pred, "viridis", lo, hi),
        ("|ToF - true| (mm)", tof_err, "magma", 0, emax),
        ("|model - true| (mm)", model_err, "magma", 0, emax),
    ]
    for ax, (title, image, cmap, vmin, vmax) in zip(axes, panels):
        im = ax.imshow(image, cmap=cmap, vmin=vmin, vmax=vmax)
        ax.set_title(title, fontsize=8)
        ax.axis("off")
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03)
    ys, xs = np.nonzero(dropout)
    axes[1].plot(xs, ys, ",", color="red")
    fig.tight_layout()
    return _png(fig)


def _training_plot(curve: list[dict]) -> str:
    import matplotlib.pyplot as plt

    losses = [(p["step"], p["loss"] * 1000) for p in curve if p.get("loss") is not None]
    fig, ax = plt.subplots(figsize=(6, 2.8))
    if losses:
        ax.plot(*zip(*losses), color="tab:blue")
    ax.set_xlabel("optimizer step")
    ax.set_ylabel("training loss (mm, masked L1)", color="tab:blue")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    a1 = [(p["step"], p["a1"]) for p in curve if p.get("a1") is not None]
    if a1:
        ax2 = ax.twinx()
        ax2.plot(*zip(*a1), "o-", color="tab:green", ms=3)
        ax2.set_ylabel("validation $\\delta<1.05$", color="tab:green")
        ax2.set_ylim(0, 1.02)
    return _png(fig)


def _value_text(value) -> str:
    """A table cell for ``value``: floats to 4 significant digits, lists joined by " / " (as the keys
    name them: "median / mean / variance"), dicts as "key: value" pairs, booleans yes / no, None "none"
    (was: JSON, "[0.1992, 0.2214, 0.01764]" and {"2": 0.082, ...})."""
    if isinstance(value, str):
        return value
    if isinstance(value, bool):
        return "yes" if value else "no"
    if value is None:
        return "none"
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, (list, tuple)):
        return " / ".join(_value_text(v) for v in value)
    if isinstance(value, dict):
        return "; ".join(f"{k}: {_value_text(v)}" for k, v in value.items())
    return str(value)


def _kv_table(items: dict) -> str:
    rows = "".join(f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(_value_text(v))}</td></tr>"
                   for k, v in items.items())
    return f"<table class='kv'>{rows}</table>"


_CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',sans-serif;margin:24px;max-width:1200px;color:#222}
h1{margin-bottom:4px} h2{border-bottom:1px solid #ccc;padding-bottom:2px;margin-top:28px}
.verdict{font-size:28px;font-weight:bold;padding:14px 18px;border-radius:6px;color:#fff}
.verdict.ok{background:#2e7d32} .verdict.bad{background:#c62828}
.reason{font-size:15px;margin-top:6px}
table{border-collapse:collapse;font-size:13px;margin:8px 0} td,th{border:1px solid #ccc;padding:3px 7px;text-align:left}
tr.pass td.v{color:#2e7d32;font-weight:bold} tr.fail td.v{color:#c62828;font-weight:bold} tr.fail{background:#fdecea}
tr.skip td{color:#777}
table.metrics td{text-align:right} img{max-width:100%} .note{color:#777;font-style:italic}
"""


def render_html(data: ReportData) -> str:
    """The report as one HTML string (plots embedded)."""
    import matplotlib

    matplotlib.use("Agg")
    parts: list[str] = []

    def section(title: str, body: str | None, key: str) -> None:
        if body is None:
            why = data.notes.get(key, "not produced by this run")
            body = f"<p class='note'>Not available: {html.escape(why)}.</p>"
        parts.append(f"<h2>{title}</h2>{body}")

    host_fault = data.fault is not None and data.fault.split(":", 1)[0] in HOST_FAULTS  # this computer's: unjudged
    verdict = "ACCEPTED" if data.accepted else ("STOPPED" if data.stopped else "NO VERDICT" if host_fault else "REJECTED")
    kind = "simulated" if data.simulated else "hardware"
    head = (
        f"<h1>Sensor {html.escape(data.serial)} &mdash; commissioning report</h1>"
        f"<div class='verdict {'ok' if data.accepted else 'bad'}'>{verdict}</div>"
    )
    if not data.accepted and data.reason:
        head += f"<p class='reason'><b>Reason:</b> {html.escape(data.reason)}</p>"
    head += f"<p>{kind} bench"
    a1_check = next((c for c in data.checks if c["name"] == "heldout_a1" and c["value"] is not None), None)
    if a1_check is not None:  # as the checks table writes it (was: 3 decimals, a failed 0.94996 shown as 0.950)
        head += f" &middot; held-out &delta;&lt;1.05 = {check_value_text(a1_check)}"
    elif data.heldout_metrics and data.heldout_metrics.get("a1") is not None:
        head += f" &middot; held-out &delta;&lt;1.05 = {data.heldout_metrics['a1']:.3f}"
    head += "</p>"
    parts.append(head)

    ran = any(c["verdict"] != NOT_RUN for c in data.checks)  # none: the note says why (an early fault)
    section("Acceptance checks", _checks_table(data.checks) if ran else None, "checks")
    section(
        "Held-out metrics (paper's columns)",
        metrics_table(
            [("fine-tuned model vs ToF, held-out poses", data.heldout_metrics,
              cell_checks(data.checks, HELDOUT_CELL_CHECKS))]
            + ([("the same, contact patches only", data.contact_metrics, cell_checks(data.checks, CONTACT_CELL_CHECKS))]
               if data.contact_metrics else [])
        )
        if data.heldout_metrics
        else None,
        "metrics",
    )
    leak = None
    if data.leak_t is not None and data.leak_hpa is not None and len(data.leak_t) >= 3:
        leak = _img(_leak_plot(data.leak_t, data.leak_hpa), "leak-test pressure trace")
    section("Leak test: pressure over the hold", leak, "leak")
    cam = None
    if data.camera_ir_mean is not None:
        cam = _img(
            _camera_plot(data.camera_ir_mean, data.camera_dead_mask, data.camera_stuck_mask, data.camera_dot_mask),
            "camera health",
        )
    section("Camera health (no-contact frames)", cam, "camera")
    fig5 = None
    if data.nocontact_valid_count is not None and data.nocontact_err_mean is not None:
        fig5 = _img(
            _map_row(
                [
                    ("valid depth count", data.nocontact_valid_count.astype(np.float32), "viridis"),
                    ("error mean (mm)", data.nocontact_err_mean * 1000, "coolwarm"),
                    ("error variance (mm$^2$)", data.nocontact_err_var * 1e6, "magma"),
                ]
            ),
            "no-contact per-pixel maps",
        )
        fig5 = "<p>Over the no-contact reference frames; error = predicted - measured ToF depth.</p>" + fig5
    section("No-contact per-pixel statistics (paper Fig. 5)", fig5, "nocontact")
    fig6 = None
    if data.example_ir is not None and data.example_pred is not None:
        fig6 = _img(
            _examples_plot(data.example_ir, data.example_depth, data.example_pred, data.example_labels, data.example_true),
            "held-out examples",
        )
    section("Held-out examples (paper Fig. 6)", fig6, "examples")
    section(
        "Fine-tuning curve",
        _img(_training_plot(data.training_curve), "training curve") if data.training_curve else None,
        "training",
    )
    if data.simulated:
        truth = None
        if data.truth_comparison:
            tc = data.truth_comparison
            truth = (
                "<p>Against the simulator's true membrane depth, on the held-out frames' membrane pixels.</p>"
                + metrics_table(
                    [("fine-tuned model vs truth, where the ToF is valid", tc["model"],
                      cell_checks(data.checks, TRUTH_CELL_CHECKS)), ("ToF vs truth, where valid", tc["tof"], {})]
                    + ([("fine-tuned model vs truth, every membrane pixel", tc["model_all"], {})] if tc.get("model_all")
                       else [])
                )
            )
            drop = tc.get("dropouts")
            if drop:
                truth += (
                    f"<p>ToF dropouts on the membrane: {drop['fraction']:.1%} of pixels "
                    f"({drop['pixels']} px over the held-out frames); the model fills them with an RMSE of "
                    f"{drop['model_rmse_mm']:.3f} mm against the truth (&delta;&lt;1.05 = {drop['model_a1']:.3f}).</p>"
                )
            if data.example_true is not None and data.example_pred is not None:
                truth += _img(
                    _truth_plot(data.example_true[0], data.example_depth[0], data.example_pred[0]),
                    "model and ToF against the true depth",
                )
        section("Model vs ToF against the true depth (simulated)", truth, "truth")
    pose = None
    if data.pose:
        pose = _kv_table(data.pose)
    section("Pose check on the mug", pose, "pose")
    if data.run_info:
        parts.append("<h2>Run</h2>" + _kv_table(data.run_info))
    body = "\n".join(parts)
    title = f"{data.serial} {verdict.lower()}"
    return (
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
        f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>{body}</body></html>\n"
    )


def write_report(data: ReportData, path: Path) -> Path:
    """Render ``data`` to ``path`` (HTML, self-contained; atomically: ``collect.atomic_files.write_text``);
    returns ``path``."""
    path = Path(path)
    write_text(path, render_html(data))
    return path
