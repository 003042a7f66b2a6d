"""Acceptance thresholds, leak-test analysis and camera health on synthetic arrays."""

import numpy as np
import pytest

from calibrate.acceptance import accepted, evaluate, load_thresholds, rejection_reason
from calibrate.camera_health import assess_camera
from calibrate.leak_test import analyse_leak
from collect.errors import InputError


def test_packaged_thresholds_load_and_gate_hardware_checks():
    th = load_thresholds()
    assert th.version == 1
    assert th["heldout_a1"].lo == 0.95
    assert th["leak_rate_hpa_per_min"].gate and not th["heldout_a1"].gate
    assert th["inflation_pressure_hpa"].limit() == ("in", [1030.0, 1110.0])


def test_lab_override_tightens_only_named_checks(tmp_path):
    path = tmp_path / "lab.yaml"
    path.write_text("version: 1\nchecks:\n  heldout_a1: {min: 0.98}\n  leak_rate_hpa_per_min: {max: 0.2}\n")
    th = load_thresholds(path)
    assert th["heldout_a1"].lo == 0.98
    assert th["leak_rate_hpa_per_min"].hi == 0.2
    assert th["dead_pixels"].hi == load_thresholds()["dead_pixels"].hi
    assert not evaluate(th, "heldout_a1", 0.97)["passed"]
    assert evaluate(load_thresholds(), "heldout_a1", 0.97)["passed"]


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("version: 1\nchecks:\n  no_such_check: {max: 1}\n", "unknown check"),
        ("version: 2\nchecks:\n  heldout_a1: {min: 0.9}\n", "version"),
        ("version: 1\nchecks:\n  heldout_a1: {min: high}\n", "finite number"),
        ("version: 1\nchecks:\n  inflation_pressure_hpa: {min: 1100, max: 1000}\n", "above max"),
        ("version: 1\nchecks: [1, 2\n", "not valid YAML: line 3, column 1: expected ',' or ']', but got '<stream end>' "
                                    r"\(while parsing a flow sequence\)"),
        ("just text\n", "must hold"),
        # was: silently ignored, the packaged limit left in force
        ("version: 1\nchecks:\n  heldout_a1: {mn: 0.99}\n", "check 'heldout_a1': unknown key 'mn' "
                                                             r"\(known: min, max, unit, gate, describe\)"),
        ("version: 1\nchecks:\n  heldout_a1: {gate: 'false'}\n", "gate must be true or false, got 'false'"),  # was: true
        ("version: true\nchecks:\n  heldout_a1: {min: 0.9}\n", "has version True"),
        # was: "has version '1'; this bubble expects version 1"
        ("version: '1'\nchecks:\n  heldout_a1: {min: 0.9}\n",
         r"version must be the number 1 \(without quotes or leading zeros\), got the text '1'"),
        ("version: 01\nchecks:\n  heldout_a1: {min: 0.9}\n",  # text since session 51 (YAML 1.1: octal 1)
         r"version must be the number 1 \(without quotes or leading zeros\), got the text '01'"),
        # limits no sensor could meet (was: accepted, then every run rejected and the rejection registered)
        ("version: 1\nchecks:\n  heldout_a1: {min: 5}\n",
         r"check 'heldout_a1': min must be in 0\.\.1 \(heldout_a1 is a fraction\), got 5$"),
        ("version: 1\nchecks:\n  leak_rate_hpa_per_min: {max: -1}\n",
         r"check 'leak_rate_hpa_per_min': max must be >= 0 \(leak_rate_hpa_per_min is a rate of pressure loss\), got -1$"),
        ("version: 1\nchecks:\n  frames_dropped_fraction: {max: 1.5}\n", "max must be in 0..1"),
        ("version: 1\nchecks:\n  pose_e_theta_median: {max: 2}\n", "max must be in 0..1"),
        ("version: 1\nchecks:\n  dead_pixels: {max: -3}\n", "max must be >= 0"),
        ("version: 1\nchecks:\n  heldout_rmse_mm: {max: -0.5}\n", "max must be >= 0"),
        ("version: 1\nchecks:\n  inflation_pressure_hpa: {min: -5, max: 1000}\n", "min must be in 500..2000"),
        # a range in Pa or kPa (was: accepted, and every sensor rejected)
        ("version: 1\nchecks:\n  inflation_pressure_hpa: {min: 103000, max: 111000}\n",
         r"check 'inflation_pressure_hpa': min must be in 500\.\.2000 \(inflation_pressure_hpa is an absolute "
         r"pressure in hPa\), got 103000$"),
        ("version: 1\nchecks:\n  inflation_pressure_hpa: {min: 103, max: 111}\n", "min must be in 500..2000"),
        # was: the packaged limit dropped, a gate's included (a leaking sensor passed its leak test)
        ("version: 1\nchecks:\n  leak_rate_hpa_per_min: {max: null, min: 0}\n",
         "check 'leak_rate_hpa_per_min': max must be a finite number, got None"),
        # was: a misspelt block ignored, its limit unused; a check given twice was its last
        ("version: 1\nchecks:\n  heldout_a1: {min: 0.9}\nchekcs:\n  heldout_rmse_mm: {max: 0.5}\n",
         r"unknown key 'chekcs' \(known: version, checks\)"),
        # was: "must hold 'version' and 'checks'", not naming the misspelt block
        ("version: 1\nchekcs:\n  heldout_rmse_mm: {max: 0.5}\n", r"unknown key 'chekcs' \(known: version, checks\)"),
        ("version: 1\nchecks:\n  heldout_a1: {min: 0.97}\n  heldout_a1: {min: 0.5}\n",
         r"not valid YAML: line 4, column 3: duplicate key 'heldout_a1': give each key once"),
        # was: a one-sided check turned into a range that rejected healthy sensors
        ("version: 1\nchecks:\n  leak_rate_hpa_per_min: {min: 0.3}\n",
         "check 'leak_rate_hpa_per_min' is a maximum check; a min alone would add a second limit"),
        ("version: 1\nchecks:\n  heldout_a1: {max: 0.99}\n",
         "check 'heldout_a1' is a minimum check; a max alone would add a second limit: give min"),
        # was: the value, computed in mm, printed and judged as 0.149 m (and a list's repr as a unit)
        ("version: 1\nchecks:\n  heldout_rmse_mm: {max: 0.0015, unit: m}\n",
         r"check 'heldout_rmse_mm' is measured in mm; its unit cannot be changed \(got 'm'\): give its limits in mm$"),
        ("version: 1\nchecks:\n  heldout_rmse_mm: {unit: [mm]}\n", r"unit must be text, got \['mm'\]"),
        ("version: 1\nchecks:\n  heldout_a1: {min: 0.9, describe: 3}\n", "describe must be text, got 3"),
    ],
)
def test_bad_threshold_files_are_one_line_input_errors(tmp_path, text, fragment):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(InputError, match=fragment) as info:
        load_thresholds(path)
    assert "\n" not in str(info.value)


def test_every_check_has_the_range_of_its_metric_and_the_packaged_limits_lie_in_it():
    from calibrate.acceptance import METRIC_RANGES

    th = load_thresholds()
    assert set(METRIC_RANGES) == set(th.checks)
    for name, (lo, hi, _) in METRIC_RANGES.items():
        for limit in (th[name].lo, th[name].hi):
            assert limit is None or lo <= limit and (hi is None or limit <= hi), name


def test_limits_at_the_ends_of_a_metric_range_are_taken(tmp_path):
    path = tmp_path / "edges.yaml"
    path.write_text("version: 1\nchecks:\n  heldout_a1: {min: 1}\n  frames_dropped_fraction: {max: 0}\n"
                    "  leak_rate_hpa_per_min: {max: 0}\n")
    th = load_thresholds(path)
    assert th["heldout_a1"].lo == 1.0 and th["frames_dropped_fraction"].hi == 0.0
    assert th["leak_rate_hpa_per_min"].hi == 0.0


def test_scientific_notation_limits_are_numbers(tmp_path):
    """Was: YAML 1.1 reads 1e-3 (no decimal point) as text: "min must be a finite number, got '1e-3'"."""
    path = tmp_path / "sci.yaml"
    path.write_text("version: 1\nchecks:\n  heldout_abs_rel: {max: 1e-3}\n  heldout_rmse_mm: {max: 15E-1}\n")
    th = load_thresholds(path)
    assert th["heldout_abs_rel"].hi == 0.001 and th["heldout_rmse_mm"].hi == 1.5


def test_missing_threshold_file_is_input_error(tmp_path):
    with pytest.raises(InputError, match="cannot read"):
        load_thresholds(tmp_path / "absent.yaml")


def test_evaluate_pass_fail_and_unmeasured():
    th = load_thresholds()
    ok = evaluate(th, "leak_rate_hpa_per_min", 0.1)
    assert ok["passed"] and ok["verdict"] == "pass" and ok["op"] == "<=" and ok["threshold"] == 1.0
    leak = evaluate(th, "leak_rate_hpa_per_min", 3.2)
    assert not leak["passed"] and "above maximum" in leak["reason"]
    low = evaluate(th, "inflation_pressure_hpa", 1000.0)
    assert not low["passed"] and "below minimum" in low["reason"]
    nan = evaluate(th, "heldout_a1", float("nan"))
    # what a failure implies is said on a failure alone (was: "353 dots within limit (is the dot pattern printed?)")
    hint = "is the dot pattern printed?"
    assert evaluate(th, "dot_count", 353, hint)["reason"] == "printed dots found in the no-contact IR image: 353 dots within limit"
    assert evaluate(th, "dot_count", 3, hint)["reason"].endswith(f"({hint})")
    assert not nan["passed"] and nan["value"] is None and "not measured" in nan["reason"]
    checks = [ok, leak]
    assert not accepted(checks) and accepted([ok]) and not accepted([])
    assert rejection_reason(checks) == "leak_rate_hpa_per_min 3.2 hPa/min (needs <= 1 hPa/min)"
    assert rejection_reason([nan], "camera-stall: no frame") == "hardware fault camera-stall: no frame; heldout_a1 not measured"


def test_leak_rate_from_a_decaying_trace():
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 20.0, 0.01) + 100.0
    leaking = 1065.0 - 3.0 / 60.0 * (t - 100.0) + rng.normal(0, 0.08, t.size)
    res = analyse_leak(t, leaking)
    assert res.rate_hpa_per_min == pytest.approx(3.0, abs=0.05)
    assert res.drop_hpa == pytest.approx(1.0, abs=0.02)
    assert res.residual_hpa == pytest.approx(0.08, rel=0.1)
    line = res.fitted_hpa()  # the report's plotted line, the one judged
    assert line[0] == pytest.approx(1065.0, abs=0.02) and line[0] - line[-1] == pytest.approx(res.drop_hpa)
    tight = analyse_leak(t, 1065.0 + rng.normal(0, 0.08, t.size))
    assert abs(tight.rate_hpa_per_min) < 0.05 and tight.mean_hpa == pytest.approx(1065.0, abs=0.01)
    with_glitch = leaking.copy()
    with_glitch[5] = np.nan
    assert analyse_leak(t, with_glitch).rate_hpa_per_min == pytest.approx(3.0, abs=0.05)
    with pytest.raises(InputError):
        analyse_leak(t[:2], leaking[:2])


def _synthetic_frames(rng, dots=True, n=8, h=96, w=128):
    yy, xx = np.mgrid[:h, :w]
    lit = 20000.0 * np.exp(-((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / (2 * 50.0**2))
    albedo = np.ones((h, w))
    if dots:
        for cy, cx in rng.uniform([4, 4], [h - 4, w - 4], size=(80, 2)):
            albedo[(yy - cy) ** 2 + (xx - cx) ** 2 < 3] = 0.15
    ir = (lit * albedo)[None] + rng.normal(0, 40.0, (n, h, w))
    ir = np.clip(ir, 0, 65535).astype(np.uint16)
    depth = np.full((n, h, w), 9000, np.uint16)
    depth[:, :12, :12] = 0  # a corner sees the housing
    return ir, depth


def test_camera_health_of_a_good_camera():
    ir, depth = _synthetic_frames(np.random.default_rng(2))
    health = assess_camera(ir, depth)
    assert health.dead_pixels == 0 and health.stuck_pixels == 0
    assert health.valid_depth_coverage == pytest.approx(1 - 144 / (96 * 128))
    assert health.dot_contrast > 0.5 and health.dot_count > 40
    assert health.valid_count.shape == (96, 128) and health.valid_count.max() == 8


def test_camera_health_finds_dead_and_stuck_clusters_and_missing_dots():
    rng = np.random.default_rng(3)
    ir, depth = _synthetic_frames(rng)
    ir[:, 40:45, 50:56] = 0  # 30 dead pixels
    ir[:, 20, 30] = 40000  # one stuck pixel
    ir[:, 60:62, 70:73] = 65535  # 6 stuck saturated pixels
    health = assess_camera(ir, depth)
    assert health.dead_pixels == 30 and health.dead_mask[42, 52]
    assert health.stuck_pixels == 7 and health.stuck_mask[20, 30]
    plain_ir, plain_depth = _synthetic_frames(rng, dots=False)
    plain = assess_camera(plain_ir, plain_depth)
    assert plain.dot_contrast < 0.2 and plain.dot_count == 0


def test_single_pixel_specks_are_not_counted_as_dots():
    rng = np.random.default_rng(5)
    ir, depth = _synthetic_frames(rng, dots=False)
    for y, x in zip(range(20, 80, 2), range(20, 110, 3)):  # 30 dark specks of one pixel each
        ir[:, y, x] //= 5
    health = assess_camera(ir, depth)
    assert health.dot_count == 0


def test_camera_health_rejects_too_few_frames():
    ir, depth = _synthetic_frames(np.random.default_rng(4), n=3)
    with pytest.raises(InputError, match="at least 4"):
        assess_camera(ir, depth)


@pytest.mark.parametrize("name, value, shown", [("heldout_a1", 0.94996, "0.94996"),
                                                ("leak_rate_hpa_per_min", 1.00004, "1.00004"),
                                                ("heldout_a1", 0.91234, "0.9123")])
def test_a_failed_value_never_reads_as_its_limit(tmp_path, name, value, shown):
    """Was: "heldout_a1 0.95 (needs >= 0.95)" and "leak_rate_hpa_per_min 1 hPa/min (needs <= 1 hPa/min)",
    failed, in the reason, the REJECTED line, the registry and the report's table."""
    from calibrate.report import ReportData, write_report

    check = evaluate(load_thresholds(), name, value)
    assert not check["passed"] and shown in check["reason"] and shown in rejection_reason([check])
    html = write_report(ReportData(serial="SB-1", accepted=False, simulated=True, reason="x", checks=[check]),
                        tmp_path / "report.html").read_text()
    assert f"<td>{shown}</td>" in html and ("&lt;= " in html or "&gt;= " in html)  # the comparison escaped


def test_a_value_reads_on_its_side_of_a_lab_limit_and_the_limit_as_written(tmp_path):
    """Lab limits with more digits than a value's 4: was "1030 hPa within limit" for a passing 1030.45
    beside a minimum of 1030.4 (the report: ``1030 | 1030.4 - 1110 | PASS``), and the TUI showed the
    limits to 4 digits (0.12345 as 0.1235, 1030.5 as 1030)."""
    from calibrate.report import ReportData, write_report
    from calibrate.tui.widgets.acceptance_table import threshold_text, value_text

    lab = tmp_path / "lab.yaml"
    lab.write_text("version: 1\nchecks:\n  inflation_pressure_hpa: {min: 1030.4}\n"
                   "  leak_rate_hpa_per_min: {max: 0.12345}\n")
    thresholds = load_thresholds(lab)
    passing = evaluate(thresholds, "inflation_pressure_hpa", 1030.45)
    assert passing["passed"] and "1030.5 hPa within limit" in passing["reason"]
    assert (value_text(passing), threshold_text(passing)) == ("1030.5 hPa", "in [1030.4, 1110] hPa")
    failing = evaluate(thresholds, "leak_rate_hpa_per_min", 0.123456)
    assert not failing["passed"] and "0.1235 hPa/min above maximum 0.12345 hPa/min" in failing["reason"]
    assert (value_text(failing), threshold_text(failing)) == ("0.1235 hPa/min", "<= 0.12345 hPa/min")
    html = write_report(ReportData(serial="SB-1", accepted=False, simulated=True, reason="x",
                                   checks=[passing, failing]), tmp_path / "report.html").read_text()
    assert "<td>1030.5</td><td>1030.4 &ndash; 1110</td>" in html and "&lt;= 0.12345" in html


@pytest.mark.parametrize("seed", [2, 4])
def test_the_housing_at_the_image_edges_is_no_dot(seed):
    """Was: on a simulated sensor printed without dots, the dark housing at the image's top and
    bottom edges passed as 1-4 dots of 0.95 contrast: dot_contrast passed, dot_count alone rejected."""
    import numpy as np

    from calibrate.camera_health import assess_camera
    from hw_mocks.bubble_sim import BubbleSim
    from hw_mocks.sensor_spec import draw_sensor

    sim = BubbleSim(draw_sensor(seed, "no-dots"), [])
    state = sim.solve(np.array([0.45, -0.3, 0.3, np.pi, 0, 0]), 0.0)
    rng = np.random.default_rng(seed)
    frames = [sim.render(state, rng) for _ in range(4)]
    health = assess_camera(np.array([f[0] for f in frames]), np.array([f[1] for f in frames]))
    assert health.dot_count == 0 and health.dot_contrast == 0.0


def test_a_thresholds_file_may_restate_a_checks_unit(tmp_path):
    path = tmp_path / "lab.yaml"
    path.write_text("version: 1\nchecks:\n  heldout_rmse_mm: {max: 0.3, unit: mm}\n"
                    "  heldout_abs_rel: {max: 0.02, unit: ''}\n")
    th = load_thresholds(path)
    assert (th["heldout_rmse_mm"].hi, th["heldout_rmse_mm"].unit, th["heldout_abs_rel"].unit) == (0.3, "mm", "")
