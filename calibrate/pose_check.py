"""The downstream pose check (the paper's Sec. V) over a recorded session.

For every ``hold`` frame of the chosen object (the mug by default) the object's pose in the
camera frame is estimated twice - from the depth predicted by the model from the IR image and
from the measured ToF depth - and the two are compared:
``e_x = ||p1 - p2||`` (mm) and ``e_theta = 1 - |q1 . q2|``, modulo the shape's symmetry (see
below). ``p1, p2`` are where the two poses put the shape's ``center`` (the cylinder's centre on its
axis, a mesh's bounding-box centre), the geometry whose pose is fitted, not the object's origin on
the fixture: the mug's lies 94 mm from its axis, and there ``e_x`` would mostly repeat the
orientation error (``e_theta``) times that lever arm. On simulated sessions both (and a
third fit on the true membrane depth) are also compared with the true object pose known from the
bench (fixture pose and arm pose), modulo the shape's symmetry (a cylinder's spin about and
shift along its axis, which no contact patch on its side can see; see ``align_symmetry``).

Each depth source gets its own contact patch against its own no-contact reference (the median of
that source over the object's ``free`` frames before its first press). Every fit starts from a
prior near the bench pose: the bench pose perturbed by a fixed, seeded offset per contact pose
(``prior_error_mm`` at the shape's centre, ``prior_error_deg`` about it; the paper's "sufficiently
close initial condition");
the following frames of the same contact pose are warm-started from the previous frame's fit of
the same source. Frames that cannot be used are counted by reason, never raised; a run without
one usable frame raises ``InputError``.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from calibrate.contact_patch import N_POINTS, contact_points
from calibrate.pose_estimation import (
    MIN_POINTS,
    Cylinder,
    Pose,
    ProximityPoseEstimator,
    Shape,
    align_symmetry,
    orientation_error,
    position_error,
    shape_from_object,
)
from collect.atomic_files import replacing
from collect.errors import InputError
from collect.output_files import PNG_WRITER_KEY, remove_earlier_png
from collect.transforms import invert, pose_to_matrix
from trainer.contact import CONTACT_THRESHOLD_M, reference_depth
from trainer.metrics import METRIC_KEYS, depth_metrics

#: Depth sources, in report order. ``true`` exists in simulated sessions only.
SOURCES = ("predicted", "measured", "true")

#: Skip reasons (keys of ``PoseCheckResult.skipped``).
SKIP_NO_CONTACT = "no_contact"  # no pixel pushed in beyond the threshold, in some source
SKIP_TOO_FEW_POINTS = "too_few_points"  # a patch with fewer than MIN_POINTS points
SKIP_NON_FINITE = "non_finite_prediction"  # the network returned NaN/inf for the frame
SKIP_FIT_FAILED = "fit_failed"  # the solver did not converge, or its poses' errors overflow


@dataclass(frozen=True)
class ErrorStats:
    """Median, mean and (population) variance of an error over the used frames."""

    median: float
    mean: float
    variance: float

    @classmethod
    def of(cls, values) -> "ErrorStats":
        v = np.asarray(values, dtype=np.float64)
        return cls(float(np.median(v)), float(np.mean(v)), float(np.var(v)))


@dataclass
class FramePoses:
    """Per used frame: the errors and the fitted poses (``[x,y,z m, qw,qx,qy,qz]`` camera frame)."""

    frame: int
    pose_id: int
    e_x_mm: float  # predicted vs measured, modulo the shape's symmetry
    e_theta: float
    n_points: dict[str, int]  # per source, points kept by the fit
    n_outliers: dict[str, int]  # per source, points the fit dropped as outliers
    rms_mm: dict[str, float]  # per source, RMS signed distance of the points at the fit
    poses: dict[str, list[float]]  # per source (+ "bench": the true pose from fixture and arm)
    #: simulated only: source -> {e_x_mm, e_theta} vs the true pose, modulo the shape's symmetry
    vs_true: dict[str, dict[str, float]] = field(default_factory=dict)


@dataclass
class PoseCheckResult:
    """Outcome of ``run_pose_check``. ``to_dict()`` is the ``bubble pose --json`` document."""

    session: str
    object_name: str
    shape: str  # "cylinder" or "mesh_sdf"
    n_hold_frames: int  # hold frames of the object in the session
    n_used: int  # frames with a pose from both predicted and measured depth (the true depth's fit may fail)
    skipped: dict[str, int]  # reason -> frames
    e_x_mm: ErrorStats  # predicted vs measured
    e_theta: ErrorStats
    hz: float  # pose estimates (contact patch + fit) per second, one core
    n_fits: int  # pose estimates ``hz`` was timed over (every source's fits, the frames skipped later included)
    vs_true: dict[str, dict[str, ErrorStats]]  # simulated only: source -> {"e_x_mm", "e_theta"}
    #: the paper's depth metrics (``trainer.metrics.depth_metrics``, its default depth range) of the
    #: predicted depth against the measured ToF depth over the object's hold frames
    depth_metrics: dict[str, float]
    frames: list[FramePoses]
    settings: dict
    #: the session's sensor serial when the model's training sessions were recorded with other sensors
    #: (``ModelMetadata.sensors_not_trained_on``; empty for an estimator without metadata)
    sensors_not_trained_on: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        """The ``--json`` document: every field, with the depth metric keys at top level."""
        data = asdict(self)
        data.update(data.pop("depth_metrics"))
        return data

    def e_x_median_by_pose(self) -> dict[int, float]:
        """Median ``e_x`` (mm, predicted vs measured) over the used frames of each contact pose."""
        by_pose: dict[int, list[float]] = {}
        for f in self.frames:
            by_pose.setdefault(f.pose_id, []).append(f.e_x_mm)
        return {pose: float(np.median(v)) for pose, v in sorted(by_pose.items())}

    def summary(self) -> str:
        """Two or three lines for the terminal."""
        lines = [
            f"pose check on {self.object_name!r}: {self.n_used}/{self.n_hold_frames} hold frames used"
            + (f" (skipped: {', '.join(f'{k} {v}' for k, v in self.skipped.items() if v)})"
               if any(self.skipped.values()) else ""),
            f"predicted vs measured depth: e_x median {self.e_x_mm.median:.3f} mm (mean "
            f"{self.e_x_mm.mean:.3f}), e_theta median {self.e_theta.median:.2e} (mean "
            f"{self.e_theta.mean:.2e}); {self.hz:.0f} pose estimates/s",
        ]
        if self.vs_true:
            lines.append("vs true pose: " + "; ".join(
                f"{src} e_x {st['e_x_mm'].median:.3f} mm, e_theta {st['e_theta'].median:.2e}"
                for src, st in self.vs_true.items()))
        return "\n".join(lines)


def bench_pose(tcp_pose, camera_in_tcp, fixture_pose) -> Pose:
    """True object pose in the camera frame: ``inv(T_base_tcp T_tcp_cam) T_base_object``.

    All three arguments are UR poses ``(6,)``: TCP in base, camera in TCP, object in base.
    """
    base_cam = pose_to_matrix(tcp_pose) @ pose_to_matrix(camera_in_tcp)
    return Pose.from_matrix(invert(base_cam) @ pose_to_matrix(fixture_pose))


def perturbed_prior(pose: Pose, rng: np.random.Generator, error_mm: float, error_deg: float,
                    center=(0.0, 0.0, 0.0)) -> Pose:
    """``pose`` turned by ``error_deg`` about ``center`` ``(3,)`` (object frame, m: the shape's centre
    in the pose check) and moved by ``error_mm``, both in random directions: ``center`` lands
    ``error_mm`` from where ``pose`` puts it. (Was: turned about the object's origin, which put the
    mug's cylinder, 94 mm from it, up to 5.3 mm off for a "2 mm, 2 deg" prior.)"""
    shift = rng.normal(size=3)
    axis = rng.normal(size=3)
    turn = Rotation.from_rotvec(np.radians(error_deg) * axis / np.linalg.norm(axis)).as_matrix()
    transform = pose.matrix()
    pivot = transform[:3, :3] @ np.asarray(center, dtype=np.float64) + transform[:3, 3]  # center, camera frame
    transform[:3, :3] = turn @ transform[:3, :3]
    transform[:3, 3] = turn @ (transform[:3, 3] - pivot) + pivot + 1e-3 * error_mm * shift / np.linalg.norm(shift)
    return Pose.from_matrix(transform)


def _frame_stats(frames: list[FramePoses]) -> dict:
    """``e_x_mm``, ``e_theta`` and ``vs_true`` (``PoseCheckResult`` fields) over ``frames``."""
    sources = [s for s in SOURCES if any(s in f.vs_true for f in frames)]  # the true depth's: where it fitted
    return {
        "e_x_mm": ErrorStats.of([f.e_x_mm for f in frames]),
        "e_theta": ErrorStats.of([f.e_theta for f in frames]),
        "vs_true": {s: {key: ErrorStats.of([f.vs_true[s][key] for f in frames if s in f.vs_true])
                        for key in ("e_x_mm", "e_theta")}
                    for s in sources},
    }


def pooled_result(results: list[PoseCheckResult]) -> PoseCheckResult:
    """One result over the frames of several runs of the same object (e.g. several sensors): the
    errors over all their frames, counts summed, ``hz`` over all their fits (their total over their
    total time: was the mean of the runs' rates, which counted a run of 10 fits as much as one of
    1000), sessions joined by ``;``."""
    frames = [f for r in results for f in r.frames]
    images = [r.depth_metrics["n_images"] for r in results]
    metrics = {k: float(np.average([r.depth_metrics[k] for r in results], weights=images)) if sum(images) else
               float("nan") for k in METRIC_KEYS}  # depth_metrics averages over images: weight each run by its own
    return PoseCheckResult(
        depth_metrics={**metrics, "n_images": int(sum(images)),
                       "n_pixels": int(sum(r.depth_metrics["n_pixels"] for r in results))},
        session="; ".join(r.session for r in results), object_name=results[0].object_name,
        shape=results[0].shape, n_hold_frames=sum(r.n_hold_frames for r in results), n_used=len(frames),
        skipped={k: sum(r.skipped[k] for r in results) for k in results[0].skipped},
        hz=_pooled_hz(results), n_fits=sum(r.n_fits for r in results), frames=frames, settings=results[0].settings,
        sensors_not_trained_on=sorted({s for r in results for s in r.sensors_not_trained_on}),
        **_frame_stats(frames),
    )


def _pooled_hz(results: list[PoseCheckResult]) -> float:
    """Pose estimates per second over all the fits of ``results``: their count over their time."""
    seconds = sum(r.n_fits / r.hz for r in results if r.hz > 0)
    return sum(r.n_fits for r in results if r.hz > 0) / seconds if seconds > 0 else 0.0


def _errors(shape: Shape, pose: Pose, reference: Pose) -> dict[str, float]:
    """``e_x`` (mm, at the shape's centre) and ``e_theta`` of ``pose`` against ``reference``,
    modulo the shape's symmetry (``pose`` aligned to ``reference`` first)."""
    aligned = align_symmetry(shape, pose, reference)
    return {"e_x_mm": 1e3 * position_error(aligned, reference, shape.center),
            "e_theta": orientation_error(aligned, reference)}


def _load_estimator(model):
    if hasattr(model, "predict_batch"):
        return model
    from trainer.inference import DepthEstimator

    return DepthEstimator.load(model)


def run_pose_check(model, session_path: str | Path, object_name: str = "mug", *,
                   threshold_m: float = CONTACT_THRESHOLD_M, n_points: int = N_POINTS,
                   prior_error_mm: float = 2.0, prior_error_deg: float = 2.0, seed: int = 0,
                   pose_ids=None, plots_dir: str | Path | None = None) -> PoseCheckResult:
    """Run the pose check over every hold frame of ``object_name`` in the session (of the contact
    poses ``pose_ids`` only, when given: e.g. the poses the model was not trained on; the session's
    ``frames/pose_id``, numbered over the whole session, not within each object).

    ``model``: a model directory (or ``"base"``), or a loaded estimator with
    ``predict_batch(ir (N,H,W) uint16) -> (N,H,W) float32 m`` (``trainer.inference.DepthEstimator``).
    ``plots_dir``: if given, histograms like the paper's Fig. 7 are written there
    (``pose_errors.png``, and ``pose_vs_true.png`` for simulated sessions).
    Raises ``InputError`` for a bad session, an unknown object, a missing no-contact reference,
    or when no frame is usable.
    """
    from collect.session_format import ATTR_CAMERA_IN_TCP
    from collect.session_reader import Session
    from trainer.evaluation import predict_frames

    if not MIN_POINTS <= int(n_points):
        raise InputError(f"points per contact patch must be at least {MIN_POINTS} (a fit needs that many), got {n_points}")
    estimator = _load_estimator(model)
    with Session.open(session_path) as session:
        obj = session.objects[session.object_id(object_name)]
        if session.camera_in_tcp is None:
            raise InputError(f"{session.path}: root attr '{ATTR_CAMERA_IN_TCP}' is missing (the camera's pose in the "
                             "TCP frame, which places the contact patch in the base frame)")
        try:
            shape = shape_from_object(obj.primitive, obj.vertices, obj.faces)
        except InputError as err:  # was: the line named neither the file nor the object
            raise InputError(f"{session.path}: object {object_name!r}: {err}") from None
        fitter = ProximityPoseEstimator(shape)
        ref_idx = session.reference_frames(object_name)
        if len(ref_idx) == 0:
            raise InputError(f"{session.path}: no no-contact (free) frames of {object_name!r} to "
                             "take the contact reference from")
        hold_idx = session.select(object=object_name, phase="hold",
                                  pose_id=None if pose_ids is None else [int(p) for p in pose_ids])
        if len(hold_idx) == 0:
            among = "" if pose_ids is None else (
                f" among pose_ids {sorted(int(p) for p in pose_ids)} (its poses: "
                f"{sorted(set(session.pose_id[session.select(object=object_name, phase='hold')].tolist()))})")
            raise InputError(f"{session.path}: no hold frames of {object_name!r}{among}")
        sources = [s for s in SOURCES if s != "true" or session.simulated]
        depth = {"predicted": predict_frames(estimator, session.ir(hold_idx)),
                 "measured": session.depth_m(hold_idx)}
        # over the frames with a finite prediction (those the check can use; was: NaN read as 0 m)
        finite = np.isfinite(depth["predicted"]).all(axis=(1, 2))
        metrics = depth_metrics(depth["predicted"][finite], depth["measured"][finite])
        ref_pred = predict_frames(estimator, session.ir(ref_idx))
        references = {"predicted": reference_depth(np.where(np.isfinite(ref_pred), ref_pred, 0.0)),
                      "measured": reference_depth(session.depth_m(ref_idx))}
        if session.simulated:  # NaN/inf pixels are invalid ones: they cost a frame its vs-true row of the
            # true depth at most (was: the whole session refused)
            depth["true"] = session.true_depth(hold_idx, finite=False)
            references["true"] = reference_depth(session.true_depth(ref_idx, finite=False))
        tcp = session.tcp_pose(hold_idx)
        pose_ids = session.pose_id[hold_idx]
        camera_in_tcp = session.camera_in_tcp
        intrinsics = session.intrinsics
        session_name = str(session.path)
        metadata = getattr(estimator, "metadata", None)
        untrained = [] if metadata is None else metadata.sensors_not_trained_on([session.sensor_serial])
        simulated = session.simulated

    skipped = {SKIP_NO_CONTACT: 0, SKIP_TOO_FEW_POINTS: 0, SKIP_NON_FINITE: 0, SKIP_FIT_FAILED: 0}
    frames: list[FramePoses] = []
    warm: dict[str, Pose] = {}
    prior = None
    last_pose_id = None
    fit_seconds = 0.0
    n_fits = 0
    for k, frame in enumerate(hold_idx):
        truth = bench_pose(tcp[k], camera_in_tcp, obj.fixture_pose)
        if pose_ids[k] != last_pose_id or prior is None:
            rng = np.random.default_rng([seed, int(pose_ids[k]) + 1])
            prior = perturbed_prior(truth, rng, prior_error_mm, prior_error_deg, shape.center)
            warm = {}
            last_pose_id = pose_ids[k]
        if not np.all(np.isfinite(depth["predicted"][k])):
            skipped[SKIP_NON_FINITE] += 1
            continue
        fits = {}
        reason = None
        for src in sources:
            start = time.perf_counter()
            points = contact_points(depth[src][k], references[src], intrinsics, threshold_m, n_points)
            if len(points) == 0:
                reason = SKIP_NO_CONTACT
            elif len(points) < MIN_POINTS:
                reason = SKIP_TOO_FEW_POINTS
            else:
                fit = fitter.fit(points, prior, start=warm.get(src))
                fit_seconds += time.perf_counter() - start
                n_fits += 1
                reason = None if fit.success else SKIP_FIT_FAILED
            if reason is None:
                fits[src] = fit
            elif src != "true":  # the simulator's own depth decides no frame's use (only its vs-true row)
                break
            else:
                reason = None
        if reason is not None:
            skipped[reason] += 1
            continue
        with np.errstate(over="ignore", invalid="ignore"):  # poses so far apart that their error overflows
            errors = _errors(shape, fits["predicted"].pose, fits["measured"].pose)
            vs_true = {s: _errors(shape, f.pose, truth) for s, f in fits.items()} if simulated else {}
        if "true" in vs_true and not np.all(np.isfinite(list(vs_true["true"].values()))):
            del fits["true"], vs_true["true"]  # as a failed fit of the simulator's depth: no vs-true row
        if not np.all(np.isfinite([v for e in (errors, *vs_true.values()) for v in e.values()])):
            skipped[SKIP_FIT_FAILED] += 1  # was: used, its e_x inf, and `--plots` a traceback
            continue
        warm = {src: fit.pose for src, fit in fits.items()}
        frames.append(FramePoses(
            frame=int(frame), pose_id=int(pose_ids[k]), **errors,
            n_points={s: f.n_points for s, f in fits.items()},
            n_outliers={s: f.n_outliers for s, f in fits.items()},
            rms_mm={s: 1e3 * f.rms_m for s, f in fits.items()},
            poses={**{s: f.pose.theta().tolist() for s, f in fits.items()}, "bench": truth.theta().tolist()},
            vs_true=vs_true,
        ))
    if not frames:
        reasons = ", ".join(f"{k} {v}" for k, v in skipped.items() if v) or "none"
        raise InputError(f"{session_name}: no usable hold frame of {object_name!r} for the pose check "
                         f"({len(hold_idx)} hold frames; skipped: {reasons})")
    result = PoseCheckResult(
        session=session_name, object_name=object_name,
        shape="cylinder" if isinstance(shape, Cylinder) else "mesh_sdf",
        n_hold_frames=int(len(hold_idx)), n_used=len(frames), skipped=skipped,
        hz=n_fits / fit_seconds if fit_seconds > 0 else 0.0, n_fits=n_fits,
        depth_metrics=metrics,
        frames=frames,
        sensors_not_trained_on=untrained,
        **_frame_stats(frames),
        settings={"threshold_m": threshold_m, "n_points": n_points, "prior_error_mm": prior_error_mm,
                  "prior_error_deg": prior_error_deg, "seed": seed,
                  "prior_weight": fitter.prior_weight, "prior_rotation_scale_m": fitter.prior_rotation_scale_m,
                  "outlier_k": fitter.outlier_k,
                  "outlier_floor_m": fitter.outlier_floor_m},
    )
    if plots_dir is not None:
        write_histograms(result, plots_dir)
    return result


#: The histograms ``write_histograms`` writes: predicted vs measured, and each source vs the true pose.
PLOT_FILES = ("pose_errors.png", "pose_vs_true.png")
#: The writer marked in each histogram PNG: ``bubble pose --plots`` replaces only images that have it
#: (``collect.output_files.check_png_output``).
PLOTS_WRITER = "bubble pose"


def write_histograms(result: PoseCheckResult, plots_dir: str | Path) -> list[Path]:
    """Histograms of the errors (the paper's Fig. 7) as PNG files in ``plots_dir``; returns their paths.

    ``pose_errors.png``: e_x (mm) and e_theta, predicted vs measured depth.
    ``pose_vs_true.png`` (simulated sessions): the same errors of each source vs the true pose; for
    a session of a real bench, an earlier ``bubble pose`` image of that name is deleted.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plots_dir = Path(plots_dir)
    plots_dir.mkdir(parents=True, exist_ok=True)
    errors_png, vs_true_png = (plots_dir / name for name in PLOT_FILES)
    written = []
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    for ax, key, label in ((axes[0], "e_x_mm", "position error $e_x$ (mm)"),
                           (axes[1], "e_theta", r"orientation error $e_\theta = 1-|q_1 \cdot q_2|$")):
        ax.hist([getattr(f, key) for f in result.frames], bins=20, color="tab:blue")
        ax.set_xlabel(label)
        ax.set_ylabel("frames")
    fig.suptitle(f"{result.object_name}: pose from predicted vs measured depth ({result.n_used} frames)",
                 parse_math=False)  # the object's name is text (a mesh cup$^$.stl read as math failed the plot)
    fig.tight_layout()
    written.append(errors_png)
    _save_figure(fig, written[-1])
    if result.vs_true:
        fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
        for ax, key, label in ((axes[0], "e_x_mm", "position error vs true pose (mm)"),
                               (axes[1], "e_theta", "orientation error vs true pose")):
            values = {src: [f.vs_true[src][key] for f in result.frames if src in f.vs_true] for src in result.vs_true}
            ax.hist(list(values.values()), bins=20, label=list(values), histtype="step", linewidth=1.5)
            ax.set_xlabel(label)
            ax.set_ylabel("frames")
            ax.legend()
        fig.suptitle(f"{result.object_name}: each depth source vs the true pose", parse_math=False)
        fig.tight_layout()
        written.append(vs_true_png)
        _save_figure(fig, written[-1])
    else:  # a session of a real bench (no true pose): an earlier run's image would read as this run's
        remove_earlier_png(vs_true_png, PLOTS_WRITER)
    return written


def _save_figure(fig, path: Path) -> None:
    """Write ``fig`` to the PNG file ``path`` atomically (``collect.atomic_files.replacing``), marked as
    ``PLOTS_WRITER``'s, and close it."""
    import matplotlib.pyplot as plt

    try:
        with replacing(path) as tmp:
            fig.savefig(tmp, dpi=100, format="png", metadata={PNG_WRITER_KEY: PLOTS_WRITER})
    finally:
        plt.close(fig)
