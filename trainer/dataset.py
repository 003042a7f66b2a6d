"""Training / evaluation frames loaded from session files into memory.

``load_frames(paths)`` reads the contact frames (``press``, ``hold``) of every object and a
share of the no-contact ``free`` frames through ``collect.session_reader.Session``, plus the
no-contact reference depth recorded before each object's first press, and keeps them at native
size; ``to_network_tensors`` turns a subset into network inputs (normalized IR, depth,
validity, contact patches) at the network's input geometry. A calibration set (~2,500 frames of
224 x 172) fits in memory easily.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from trainer.contact import contact_mask, drop_specks, reference_depth
from collect.errors import InputError
from collect.session_reader import Session
from trainer.preprocessing import InputGeometry, IRNormalization

#: Phases whose frames show the membrane in contact (the training frames of the paper).
CONTACT_PHASES = ("press", "hold")

#: Free (no-contact) frames kept, as a fraction of the contact frames of a session.
FREE_FRAME_FRACTION = 0.1

#: No-contact frames (evenly spaced) that make up one reference depth map.
REFERENCE_FRAMES = 32

#: Depth decrease from the no-contact reference (m) that puts a pixel in a contact patch for the
#: loss weighting (lower than the acceptance's 1.5 mm so that the rims of a dent count too).
CONTACT_LOSS_THRESHOLD_M = 0.5e-3

#: Contact patches of fewer pixels (8-connected) are ToF noise past the threshold, not contact.
CONTACT_MIN_PIXELS = 5


@dataclass(frozen=True)
class SessionSource:
    """Provenance of the frames of one session file (recorded in model metadata)."""

    path: str
    sha256: str
    sensor_serial: str
    simulated: bool
    n_frames: int  # frames taken from the file

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class FrameSet:
    """Frames of one or more sessions, native size, in memory (N frames)."""

    ir: np.ndarray  # (N,H,W) uint16 amplitude
    depth: np.ndarray  # (N,H,W) float32 m ToF depth, 0 = invalid
    true_depth: np.ndarray | None  # (N,H,W) float32 m, only when every session is simulated (and with_truth)
    session: np.ndarray  # (N,) int index into sources
    object_name: np.ndarray  # (N,) str object pressed ("" for none)
    pose_id: np.ndarray  # (N,) int32 contact pose within its session (-1 = none)
    phase: np.ndarray  # (N,) str phase name
    reference: np.ndarray  # (R,H,W) float32 m no-contact reference depths, 0 = never valid
    reference_index: np.ndarray  # (N,) int index into reference: the one of each frame's session and object
    sources: list[SessionSource] = field(default_factory=list)

    def __len__(self) -> int:
        return int(self.ir.shape[0])

    @property
    def size(self) -> tuple[int, int]:
        """(height, width) of the frames."""
        return int(self.ir.shape[1]), int(self.ir.shape[2])

    def subset(self, idx: np.ndarray) -> "FrameSet":
        """The frames ``idx`` ``(n,) int`` (same sources)."""
        return FrameSet(
            ir=self.ir[idx],
            depth=self.depth[idx],
            true_depth=None if self.true_depth is None else self.true_depth[idx],
            session=self.session[idx],
            object_name=self.object_name[idx],
            pose_id=self.pose_id[idx],
            phase=self.phase[idx],
            reference=self.reference,
            reference_index=self.reference_index[idx],
            sources=self.sources,
        )

    def sources_used(self) -> list[SessionSource]:
        """The sources that hold frames of this set, in order, each with ``n_frames`` its frames here."""
        counts = np.bincount(self.session, minlength=len(self.sources))
        return [replace(source, n_frames=int(n)) for source, n in zip(self.sources, counts) if n]

    def contact(self) -> np.ndarray:
        """``(N,H,W) bool``: pixels whose ToF depth is pushed in from the frame's no-contact
        reference by more than ``CONTACT_LOSS_THRESHOLD_M`` (the contact patches)."""
        mask = np.zeros(self.depth.shape, dtype=bool)
        for r in np.unique(self.reference_index):
            mine = self.reference_index == r
            mask[mine] = drop_specks(contact_mask(self.depth[mine], self.reference[r], CONTACT_LOSS_THRESHOLD_M),
                                     CONTACT_MIN_PIXELS)
        return mask


def check_each_session_once(paths_by_option: dict[str, list[str | Path]]) -> None:
    """Raise ``InputError`` when one session file (the same file, also through a link) is named
    twice, within one option's list or in two of them (``{"--data": [...], "--val-data": [...]}``)."""
    given: dict[Path, str] = {}
    for option, paths in paths_by_option.items():
        for path in paths:
            key = Path(path).resolve()
            if key in given:
                where = f"twice in {option}" if given[key] == option else f"in both {given[key]} and {option}"
                raise InputError(f"session {path} is given {where}; give each session once")
            given[key] = option


def check_each_recording_once(sources_by_option: dict[str, list[SessionSource]]) -> None:
    """Raise ``InputError`` when two session files hold the same recording (one SHA-256: a copy under
    another name), within one option's list or in two of them (``check_each_session_once``'s options)."""
    given: dict[str, tuple[str, str]] = {}
    for option, sources in sources_by_option.items():
        for source in sources:
            if source.sha256 in given:
                first, first_option = given[source.sha256]
                where = option if first_option == option else f"{first_option} and {option}"
                raise InputError(f"sessions {first} and {source.path} ({where}) are copies of one recording; "
                                 "give it once")
            given[source.sha256] = (source.path, option)


def file_sha256(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _select_frames(
    s: Session, objects: list[str] | None, phases: tuple[str, ...], free_fraction: float, stride: int, rng
) -> np.ndarray:
    names = [n for n in s.object_names if objects is None or n in objects]
    if not names:
        return np.zeros(0, dtype=np.int64)
    contact = s.select(object=names, phase=list(phases))[::stride]
    free = s.select(object=names, phase="free")
    n_free = min(len(free), int(round(free_fraction * len(contact))))
    chosen_free = np.sort(rng.choice(free, size=n_free, replace=False)) if n_free else free[:0]
    return np.union1d(contact, chosen_free)


def _reference_depth(s: Session, name: str) -> np.ndarray:
    """No-contact reference depth ``(H,W) float32 m`` of object ``name`` ("" = none) in session
    ``s``: its own reference frames, else every free frame of the session, else zeros."""
    idx = s.reference_frames(name) if name else np.zeros(0, dtype=np.int64)
    if len(idx) == 0:
        idx = s.select(phase="free")
    if len(idx) == 0:
        return np.zeros((s.height, s.width), dtype=np.float32)
    pick = np.unique(np.linspace(0, len(idx) - 1, min(len(idx), REFERENCE_FRAMES)).round().astype(np.int64))
    return reference_depth(s.depth_m(idx[pick]))


def load_frames(
    paths: list[str | Path],
    objects: list[str] | None = None,
    phases: tuple[str, ...] = CONTACT_PHASES,
    free_fraction: float = FREE_FRAME_FRACTION,
    seed: int = 0,
    stride: int = 1,
    with_truth: bool = True,
) -> FrameSet:
    """Frames of ``paths`` in ``phases`` (plus ``free_fraction`` free frames) of ``objects`` (None = all).

    ``stride`` keeps every stride-th matching frame of a session (consecutive frames of a press
    are nearly alike; pretraining on many sessions uses it to bound memory). ``with_truth``: read the
    simulator's true depth too (``FrameSet.true_depth``; the training, which never uses it, leaves it:
    it is 40 % of the frames' memory).

    A session without any matching frame adds nothing (and is not among the sources). Raises
    ``InputError`` for unreadable sessions, sessions of different frame sizes, unknown objects
    (named in no session) and when no session has a matching frame.
    """
    if not paths:
        raise InputError("no session files given")
    if stride < 1:
        raise InputError(f"frame stride must be at least 1, got {stride}")
    parts: dict[str, list] = {k: [] for k in ("ir", "depth", "true", "session", "object", "pose", "phase", "ref_index")}
    references: list[np.ndarray] = []
    sources: list[SessionSource] = []
    size = None
    known_objects: set[str] = set()
    for k, path in enumerate(paths):
        with Session.open(path) as s:
            if size is not None and (s.height, s.width) != size:
                raise InputError(
                    f"{path}: frames are {s.width}x{s.height}, other sessions are {size[1]}x{size[0]}"
                )
            size = (s.height, s.width)
            known_objects.update(s.object_names)
            sha256 = file_sha256(path)
            # the free frames a session gives depend on it and the seed alone (was: one generator for all,
            # so on the sessions listed before it)
            rng = np.random.default_rng([seed, int(sha256[:16], 16)])
            idx = _select_frames(s, objects, phases, free_fraction, stride, rng)
            if len(idx) == 0:
                continue
            depth = s.depth_m(idx)
            parts["ir"].append(s.ir(idx))
            parts["depth"].append(depth)
            parts["true"].append(s.true_depth(idx) if s.simulated and with_truth else None)
            parts["session"].append(np.full(len(idx), len(sources), dtype=np.int64))
            names = np.array(s.object_names + [""], dtype=object)
            parts["object"].append(names[s.object_index[idx]])
            ref_index = np.zeros(len(idx), dtype=np.int64)
            for oid in np.unique(s.object_index[idx]):
                references.append(_reference_depth(s, names[oid]))
                ref_index[s.object_index[idx] == oid] = len(references) - 1
            parts["ref_index"].append(ref_index)
            parts["pose"].append(s.pose_id[idx])
            parts["phase"].append(np.asarray(s.phase_name(idx), dtype=object))
            sources.append(SessionSource(str(path), sha256, s.sensor_serial, s.simulated, len(idx)))
    if objects is not None:
        unknown = sorted(set(objects) - known_objects)
        if unknown:
            raise InputError(f"unknown object {unknown[0]!r} (sessions hold: {', '.join(sorted(known_objects))})")
    if not sources:
        raise InputError(f"no {'/'.join(phases)} frames in {', '.join(str(p) for p in paths)}")
    truths = parts["true"]
    return FrameSet(
        ir=np.concatenate(parts["ir"]),
        depth=np.concatenate(parts["depth"]),
        true_depth=None if any(t is None for t in truths) else np.concatenate(truths),
        session=np.concatenate(parts["session"]),
        object_name=np.concatenate(parts["object"]),
        pose_id=np.concatenate(parts["pose"]),
        phase=np.concatenate(parts["phase"]),
        reference=np.stack(references),
        reference_index=np.concatenate(parts["ref_index"]),
        sources=sources,
    )


@dataclass
class NetworkTensors:
    """Frames at the network's input geometry (n frames, input size h x w)."""

    x: torch.Tensor  # (n,1,h,w) float32 normalized IR, 0 in the padding
    depth: torch.Tensor  # (n,1,h,w) float32 m ToF depth, 0 = invalid or padding
    content: torch.Tensor  # (1,1,h,w) bool, True where the native frame lies in the input
    contact: torch.Tensor  # (n,1,h,w) bool contact patches (FrameSet.contact), False in the padding

    def __len__(self) -> int:
        return int(self.x.shape[0])


def to_network_tensors(frames: FrameSet, geometry: InputGeometry, normalization: IRNormalization) -> NetworkTensors:
    """Normalized, padded (and scaled, if the geometry says so) tensors of ``frames``."""
    x = geometry.to_input(normalization.apply(frames.ir))
    depth = geometry.to_input(frames.depth, nearest=True)
    content = geometry.to_input(np.ones((1,) + frames.size, dtype=np.uint8), nearest=True).astype(bool)
    contact = geometry.to_input(frames.contact().astype(np.uint8), nearest=True).astype(bool)
    return NetworkTensors(
        x=torch.from_numpy(x[:, None]),
        depth=torch.from_numpy(depth[:, None]),
        content=torch.from_numpy(content[:, None]),
        contact=torch.from_numpy(contact[:, None]),
    )
