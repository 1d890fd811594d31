"""Expression spaces: the codes that drive the deformation MLP.

A space is a property of a trained model (named in its config, exposed by the server):

- ``ict53`` (embedded default): the 53 ICT-FaceKit blendshape weights, in the order of
  ``expression_names`` in ``ict_facekit.npz`` (``browDown_L`` ... ``noseSneer_R``), weights
  nominally in [0, 1]. ARKit-52 names (Apple ARKit, MediaPipe, Live Link Face) are accepted in
  name->weight maps: ``xxxLeft``/``xxxRight`` -> ``xxx_L``/``xxx_R``; ``browInnerUp`` and
  ``cheekPuff`` drive both sides; ``tongueOut`` (and MediaPipe's ``_neutral``) are ignored;
  a leading capital (Live Link Face's ``EyeBlinkLeft``) is accepted.
- ``flame120`` (paper preset): FLAME expression coefficients 100 (``expr_000`` ... ``expr_099``)
  + jaw rotation 6D (``jaw_r6d_0..5``) + left and right eye rotations 6D (``eyeL_r6d_0..5``,
  ``eyeR_r6d_0..5``) + eyelids 2 (``eyelid_L``, ``eyelid_R``) = 120.
  6D rotation = first two columns of R, ``[R00, R10, R20, R01, R11, R21]`` (``rotations.py``).

``neutral()`` is the code of the rest face: all zeros for ``ict53``; for ``flame120`` zeros
except the three 6D blocks, which hold the identity rotation ``[1, 0, 0, 0, 1, 0]``. Names
missing from a name->weight map take their neutral value.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from .rotations import IDENTITY_6D, axis_angle_to_matrix, matrix_to_rotation_6d, rotation_6d_to_matrix

__all__ = [
    "ExpressionSpace",
    "get_space",
    "SPACE_NAMES",
    "ICT53_NAMES",
    "FLAME120_NAMES",
    "ARKIT52_NAMES",
    "arkit_to_ict53",
    "flame120_from_axis_angle",
    "rotation_6d_to_matrix",
    "matrix_to_rotation_6d",
    "axis_angle_to_matrix",
]

# ICT-FaceKit expression_names, in archive order (== the ict53 vector layout).
ICT53_NAMES: tuple[str, ...] = (
    "browDown_L", "browDown_R", "browInnerUp_L", "browInnerUp_R", "browOuterUp_L", "browOuterUp_R",
    "cheekPuff_L", "cheekPuff_R", "cheekSquint_L", "cheekSquint_R", "eyeBlink_L", "eyeBlink_R",
    "eyeLookDown_L", "eyeLookDown_R", "eyeLookIn_L", "eyeLookIn_R", "eyeLookOut_L", "eyeLookOut_R",
    "eyeLookUp_L", "eyeLookUp_R", "eyeSquint_L", "eyeSquint_R", "eyeWide_L", "eyeWide_R",
    "jawForward", "jawLeft", "jawOpen", "jawRight", "mouthClose", "mouthDimple_L", "mouthDimple_R",
    "mouthFrown_L", "mouthFrown_R", "mouthFunnel", "mouthLeft", "mouthLowerDown_L", "mouthLowerDown_R",
    "mouthPress_L", "mouthPress_R", "mouthPucker", "mouthRight", "mouthRollLower", "mouthRollUpper",
    "mouthShrugLower", "mouthShrugUpper", "mouthSmile_L", "mouthSmile_R", "mouthStretch_L",
    "mouthStretch_R", "mouthUpperUp_L", "mouthUpperUp_R", "noseSneer_L", "noseSneer_R",
)  # fmt: skip

# Apple ARKit's 52 blendshape locations (MediaPipe and Live Link Face use the same names).
ARKIT52_NAMES: tuple[str, ...] = (
    "eyeBlinkLeft", "eyeLookDownLeft", "eyeLookInLeft", "eyeLookOutLeft", "eyeLookUpLeft", "eyeSquintLeft",
    "eyeWideLeft", "eyeBlinkRight", "eyeLookDownRight", "eyeLookInRight", "eyeLookOutRight", "eyeLookUpRight",
    "eyeSquintRight", "eyeWideRight", "jawForward", "jawLeft", "jawRight", "jawOpen", "mouthClose",
    "mouthFunnel", "mouthPucker", "mouthLeft", "mouthRight", "mouthSmileLeft", "mouthSmileRight",
    "mouthFrownLeft", "mouthFrownRight", "mouthDimpleLeft", "mouthDimpleRight", "mouthStretchLeft",
    "mouthStretchRight", "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper",
    "mouthPressLeft", "mouthPressRight", "mouthLowerDownLeft", "mouthLowerDownRight", "mouthUpperUpLeft",
    "mouthUpperUpRight", "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight",
    "cheekPuff", "cheekSquintLeft", "cheekSquintRight", "noseSneerLeft", "noseSneerRight", "tongueOut",
)  # fmt: skip

# Live Link Face's head and eye rotations (its CSV and stream carry them beside the 52 shapes), lower case.
_POSE_NAMES = frozenset(f"{part}{axis}".lower() for part in ("Head", "LeftEye", "RightEye") for axis in ("Yaw", "Pitch", "Roll"))


def _fold(name: str) -> str:
    """``name`` without case, ``_``, ``-`` and spaces (``jaw_open`` and ``JawOpen`` -> ``jawopen``):
    how a misspelt expression name is matched to an accepted one in error messages."""
    return name.lower().replace("_", "").replace("-", "").replace(" ", "")


# Unknown names longer than this get no "did you mean" (the longest accepted name has 19 characters).
_MAX_SUGGESTED_LEN = 40

# ARKit / MediaPipe names with no ict53 counterpart: accepted and ignored.
_ICT53_IGNORED = frozenset({"tongueOut", "_neutral"})

FLAME120_NAMES: tuple[str, ...] = (
    tuple(f"expr_{i:03d}" for i in range(100))
    + tuple(f"jaw_r6d_{i}" for i in range(6))
    + tuple(f"eyeL_r6d_{i}" for i in range(6))
    + tuple(f"eyeR_r6d_{i}" for i in range(6))
    + ("eyelid_L", "eyelid_R")
)

# Layout of flame120 (start, stop) slices.
FLAME120_EXPR = slice(0, 100)
FLAME120_JAW = slice(100, 106)
FLAME120_EYE_L = slice(106, 112)
FLAME120_EYE_R = slice(112, 118)
FLAME120_EYELIDS = slice(118, 120)


def _arkit_aliases() -> dict[str, tuple[int, ...]]:
    """ARKit name -> ict53 indices it drives."""
    index = {n: i for i, n in enumerate(ICT53_NAMES)}
    out: dict[str, tuple[int, ...]] = {}
    for name in ARKIT52_NAMES:
        if name in _ICT53_IGNORED:
            continue
        if name in index:  # jawLeft, mouthRight, jawOpen, ...: same name in both
            out[name] = (index[name],)
        elif name.endswith("Left"):
            out[name] = (index[name[: -len("Left")] + "_L"],)
        elif name.endswith("Right"):
            out[name] = (index[name[: -len("Right")] + "_R"],)
        else:  # browInnerUp, cheekPuff: one ARKit shape, two ICT sides
            out[name] = (index[name + "_L"], index[name + "_R"])
    return out


@dataclass(frozen=True, eq=False)
class ExpressionSpace:
    """A named expression-code layout with validation.

    Attributes:
        name: ``"ict53"`` or ``"flame120"``.
        names: one name per code dimension (``list[str]``, a copy).
        dim: code length E.
    """

    name: str
    _names: tuple[str, ...]
    _neutral: tuple[float, ...]
    # Extra accepted names in name->weight maps -> indices they set (e.g. ARKit names).
    _aliases: Mapping[str, tuple[int, ...]] = field(default_factory=dict)
    _ignored: frozenset[str] = frozenset()

    @property
    def names(self) -> list[str]:
        return list(self._names)

    @property
    def dim(self) -> int:
        return len(self._names)

    def __repr__(self) -> str:
        return f"ExpressionSpace({self.name!r}, dim={self.dim})"

    def neutral(self) -> Tensor:
        """The rest-face code ``[E]`` (float32): zeros, identity rotations for 6D blocks."""
        return torch.tensor(self._neutral, dtype=torch.float32)

    # ------------------------------------------------------------ parsing
    def _lookup(self, key: str) -> tuple[int, ...] | None:
        """Indices for a name, () for an ignored name, None for an unknown one."""
        for k in (key, key[:1].lower() + key[1:]):
            if k in self._ignored:
                return ()
            if k in self._index:
                return (self._index[k],)
            if k in self._aliases:
                return self._aliases[k]
        return None

    def __post_init__(self) -> None:
        if len(self._neutral) != len(self._names):
            raise ValueError(f"expression space {self.name!r}: {len(self._names)} names but {len(self._neutral)} neutral values")
        object.__setattr__(self, "_index", {n: i for i, n in enumerate(self._names)})

    def _weight(self, key: str, value: Any) -> float:
        if isinstance(value, Tensor) and value.numel() == 1:
            value = value.item()
        elif isinstance(value, np.ndarray) and value.size == 1:
            value = value.item()
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise ValueError(
                f"expression space {self.name!r}: weight for {key!r} must be a number, got {type(value).__name__} {value!r}"
            )
        v = float(value)
        if not math.isfinite(v):
            raise ValueError(f"expression space {self.name!r}: weight for {key!r} must be finite, got {v}")
        return v

    def _parse_map(self, value: Mapping[Any, Any]) -> Tensor:
        out = list(self._neutral)
        set_by: dict[int, str] = {}
        unknown = []
        index = self._index
        for key, w in value.items():
            if not isinstance(key, str):
                raise ValueError(f"expression space {self.name!r}: names must be strings, got {type(key).__name__} {key!r}")
            idx = self._lookup(key)
            if idx is None:
                unknown.append(key)
                continue
            weight = self._weight(key, w)
            for i in idx:
                if i in set_by:
                    raise ValueError(
                        f"expression space {self.name!r}: {self._names[i]!r} is set twice (by {set_by[i]!r} and {key!r})"
                    )
                set_by[i] = key
                out[i] = weight
        if unknown:
            hint = " (ARKit-52 names are accepted too)" if self._aliases else ""
            poses = [k for k in unknown if str(k).lower() in _POSE_NAMES]
            if poses:  # Live Link Face streams head and eye rotations beside the 52 blendshapes
                hint += (
                    f"; {poses[:3]}: head/eye rotations of Live Link Face, not expressions: "
                    "leave them out and turn the head with the camera"
                )
            sided = {k: s for k in unknown[:8] if (s := self._sided(str(k)))}
            if sided:  # "eyeBlink", "mouthSmile": the shapes come per side
                hint += "; " + ", ".join(f"{k!r} comes per side: {' and '.join(map(repr, s))}" for k, s in sided.items())
            # "jawOpne", "jaw_open": a typo of an accepted name (still refused: nothing is guessed on the wire).
            # Only the first such name is looked up: a stream of unknown names must stay cheap to refuse.
            typo = next((k for k in unknown if k not in sided and str(k).lower() not in _POSE_NAMES), None)
            if typo is not None and (meant := self._closest(str(typo))):
                hint += f"; did you mean {meant!r} for {typo!r}?"
            elif typo is not None and (within := self._containing(str(typo))):  # "smile", "blink": part of a name
                hint += f"; names containing {typo!r}: {within}"
            raise ValueError(
                f"expression space {self.name!r}: unknown name(s) {unknown[:8]}{'...' if len(unknown) > 8 else ''}; "
                f"expected names like {list(index)[:3]}{hint}"
            )
        return torch.tensor(out, dtype=torch.float32)

    def _folded(self) -> tuple[dict[str, str], dict[str, list[str]]]:
        """``(folded, near)``, built once per space: accepted names (the space's, then its aliases such
        as ARKit's, then those accepted and ignored) by their folded form (:func:`_fold`; the first name of a form wins), and by each
        folded form with one character deleted (to find one-edit typos with dictionary lookups)."""
        built = self.__dict__.get("_folded_names")
        if built is None:
            folded: dict[str, str] = {}
            for n in (*self._names, *self._aliases, *sorted(self._ignored)):  # tongueOut: accepted, ignored
                folded.setdefault(_fold(n), n)
            near: dict[str, list[str]] = {}
            for f, n in folded.items():
                for v in {f[:i] + f[i + 1 :] for i in range(len(f))}:
                    near.setdefault(v, []).append(n)
            built = (folded, near)
            object.__setattr__(self, "_folded_names", built)
        return built

    def _closest(self, key: str) -> str | None:
        """The accepted name that ``key`` most likely misspells, or None: the same letters up to
        case, ``_``, ``-`` and spaces first, else a name one edit away from those folded letters (a
        letter added, dropped, changed, or two swapped; "symmetric delete" lookups, a few dozen
        dictionary probes, so refusing a stream of unknown names stays cheap). Only for the error
        message: an unknown name is refused all the same."""
        if len(key) > _MAX_SUGGESTED_LEN:  # no accepted name is this long: nothing to compare
            return None
        folded, near = self._folded()
        k = _fold(key)
        if k in folded:
            return folded[k]
        hits: list[str] = []
        for v in (k, *(k[:i] + k[i + 1 :] for i in range(len(k)))):
            if v in folded:  # one letter too many
                hits.append(folded[v])
            hits.extend(near.get(v, ()))  # one letter dropped (v == k), changed or swapped
        return min(hits, key=lambda n: (abs(len(_fold(n)) - len(k)), hits.index(n))) if hits else None

    def _containing(self, key: str, limit: int = 6) -> list[str]:
        """The space's own names whose folded letters (:func:`_fold`) contain ``key``'s, at most
        ``limit`` of them (``smile`` -> ``mouthSmile_L``, ``mouthSmile_R``); none for a key under 3 or
        over ``_MAX_SUGGESTED_LEN`` letters. Only for the error message, for the first unknown name that
        is no typo: one pass over the names."""
        k = _fold(key)
        if not 3 <= len(k) <= _MAX_SUGGESTED_LEN:
            return []
        return [n for n in self._names if k in _fold(n)][:limit]

    def _sided(self, key: str) -> tuple[str, str] | None:
        """The left and right names a side-less name stands for (``eyeBlink`` -> ``eyeBlinkLeft``,
        ``eyeBlinkRight`` where those ARKit names are accepted, else ``eyeBlink_L``, ``eyeBlink_R``)."""
        for left, right in (("Left", "Right"), ("_L", "_R")):
            pair = (key + left, key + right)
            if all(self._lookup(n) for n in pair):
                return pair
        if len(key) > _MAX_SUGGESTED_LEN:
            return None
        folded, k = self._folded()[0], _fold(key)  # "eyeblink", "eye_blink": the same up to case and "_"
        for left, right in (("left", "right"), ("l", "r")):
            if k + left in folded and k + right in folded:
                return folded[k + left], folded[k + right]
        return None

    def _parse_vector(self, value: Any) -> Tensor:
        try:
            if isinstance(value, Tensor):
                t = value.detach().to(device="cpu", dtype=torch.float32)
            else:
                arr = np.asarray(value)
                if arr.dtype == object or arr.dtype.kind not in "biuf":
                    raise TypeError(f"dtype {arr.dtype}")
                if arr.dtype.kind == "b":
                    raise TypeError("booleans")
                t = torch.from_numpy(arr.astype(np.float32))
        except (TypeError, ValueError) as e:
            raise ValueError(f"expression space {self.name!r}: expected {self.dim} numbers, got non-numeric values ({e})") from None
        if tuple(t.shape) != (self.dim,):
            raise ValueError(f"expression space {self.name!r}: expected a vector of {self.dim} values, got shape {list(t.shape)}")
        if not torch.isfinite(t).all():
            bad = int((~torch.isfinite(t)).nonzero()[0])
            raise ValueError(
                f"expression space {self.name!r}: values must be finite, got {float(t[bad])} at index {bad} ({self._names[bad]})"
            )
        return t.clone()

    def parse(self, value: Any) -> Tensor:
        """A code ``[E]`` (float32, CPU) from a vector of length E or a name->weight map.

        Vectors: list, tuple, ``np.ndarray`` or ``Tensor``. Maps: names of this space (or its
        aliases, e.g. ARKit names for ict53); missing names take their neutral value.
        Raises ``ValueError`` naming the space for a wrong length, non-finite or non-numeric
        values, and unknown names.
        """
        if isinstance(value, Mapping):
            return self._parse_map(value)
        if isinstance(value, (str, bytes)) or value is None:
            raise ValueError(
                f"expression space {self.name!r}: expected a vector of {self.dim} numbers or a name->weight map, got {type(value).__name__}"
            )
        return self._parse_vector(value)

    def parse_batch(self, values: Any) -> Tensor:
        """Codes ``[B, E]`` from a ``[B, E]`` array/tensor or a sequence of vectors / maps."""
        if isinstance(values, Tensor) or isinstance(values, np.ndarray):
            if values.ndim != 2:
                raise ValueError(f"expression space {self.name!r}: expected a [B, {self.dim}] batch, got shape {list(values.shape)}")
            values = list(values)
        if isinstance(values, Mapping) or not isinstance(values, Sequence) or isinstance(values, (str, bytes)):
            raise ValueError(f"expression space {self.name!r}: expected a sequence of codes, got {type(values).__name__}")
        if not values:
            return torch.zeros(0, self.dim)
        return torch.stack([self.parse(v) for v in values])


def _make_ict53() -> ExpressionSpace:
    return ExpressionSpace("ict53", ICT53_NAMES, (0.0,) * len(ICT53_NAMES), _arkit_aliases(), _ICT53_IGNORED)


def _make_flame120() -> ExpressionSpace:
    neutral = [0.0] * len(FLAME120_NAMES)
    for sl in (FLAME120_JAW, FLAME120_EYE_L, FLAME120_EYE_R):
        neutral[sl] = IDENTITY_6D
    return ExpressionSpace("flame120", FLAME120_NAMES, tuple(neutral))


_FACTORIES = {"ict53": _make_ict53, "flame120": _make_flame120}
SPACE_NAMES: tuple[str, ...] = tuple(_FACTORIES)


def get_space(name: str) -> ExpressionSpace:
    """The expression space called ``name`` (``"ict53"`` or ``"flame120"``)."""
    if isinstance(name, ExpressionSpace):
        return name
    if name not in _FACTORIES:
        raise ValueError(f"unknown expression space {name!r}; expected one of {list(SPACE_NAMES)}")
    return _FACTORIES[name]()


def arkit_to_ict53(weights: Mapping[str, float]) -> Tensor:
    """An ARKit-52 (or ict53) name->weight map as an ict53 code ``[53]``."""
    return get_space("ict53").parse(weights)


def _as_tensor(x: Any, what: str, last: int | None) -> Tensor:
    t = torch.as_tensor(np.asarray(x) if not isinstance(x, Tensor) else x, dtype=torch.float32)
    if last is not None and (t.ndim == 0 or t.shape[-1] != last):
        raise ValueError(f"flame120_from_axis_angle: {what} must have shape [..., {last}], got {list(t.shape)}")
    if not torch.isfinite(t).all():
        raise ValueError(f"flame120_from_axis_angle: {what} must be finite")
    return t


def flame120_from_axis_angle(expr: Any, jaw: Any, eyes: Any, eyelids: Any | None = None) -> Tensor:
    """VHAP / NeRSemble FLAME parameters -> ``flame120`` codes.

    Args:
        expr: ``[..., <=100]`` FLAME expression coefficients (fewer than 100 are zero-padded,
            which is what a truncated PCA basis means).
        jaw: ``[..., 3]`` jaw axis-angle.
        eyes: ``[..., 6]`` eye axis-angles, left eye then right eye (FLAME ``eye_pose``).
        eyelids: ``[..., 2]`` (left, right) or None for zeros.
    Returns:
        ``[..., 120]`` = expr 100 ++ 6D(jaw) ++ 6D(left eye) ++ 6D(right eye) ++ eyelids 2, where
        6D(R) = first two columns of R ``[R00, R10, R20, R01, R11, R21]``.
    """
    expr = _as_tensor(expr, "expr", None)
    if expr.ndim == 0 or expr.shape[-1] > 100:
        raise ValueError(f"flame120_from_axis_angle: expr must have shape [..., <=100], got {list(expr.shape)}")
    jaw = _as_tensor(jaw, "jaw", 3)
    eyes = _as_tensor(eyes, "eyes", 6)
    lead = expr.shape[:-1]
    if eyelids is None:
        eyelids = torch.zeros(*lead, 2)
    eyelids = _as_tensor(eyelids, "eyelids", 2)
    for what, t in (("jaw", jaw), ("eyes", eyes), ("eyelids", eyelids)):
        if t.shape[:-1] != lead:
            raise ValueError(
                f"flame120_from_axis_angle: {what} must share the leading shape {list(lead)} of expr, got {list(t.shape)}"
            )
    if expr.shape[-1] < 100:
        expr = torch.cat([expr, torch.zeros(*lead, 100 - expr.shape[-1])], dim=-1)
    r6 = [matrix_to_rotation_6d(axis_angle_to_matrix(a.double())).float() for a in (jaw, eyes[..., :3], eyes[..., 3:])]
    return torch.cat([expr, *r6, eyelids], dim=-1)
