"""The ICT-FaceKit head model (USC ICT, MIT licence) in our conventions.

The shipped asset ``assets/headmodel/ict_facekit.npz`` is the "light" ICT-FaceKit model packed
from its OBJ files (see ``assets/headmodel/README.md``; licence in
``LICENSE-ICT-FaceKit.txt``). The archive stores centimetres; this module gives

- vertices in **metres**, the axes of docs/conventions.md (+x subject's left, +y up, +z out of the face);
- **centred on the head**: the origin is ``HeadModel.center_cm`` of the *generic* neutral mesh,
  x = 0 (the mesh is symmetric), y = midway between the chin (landmark 8) and the crown (highest
  head vertex), z = midway between the back of the skull (lowest z of the head vertices above the
  chin) and the nose tip (landmark 30). It is about eye level, 2 cm in front of the ears' line,
  so a head sits at the origin and a camera 1 m away with a 20 degree field of view frames it.
  The centre is one fixed offset: identity and expression deltas move vertices relative to it.

``vertices(identity [100], expression [53])`` = neutral + identity @ identity_basis +
expression @ expression_basis. Expression weights are the ``ict53`` space (order = the archive's
``expression_names``), in [0, 1]; identity weights are ~ N(0, 1) per mode.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["HeadModel", "DEFAULT_ASSET", "SHADING_HELPER_MATERIALS", "HEAD_VERTEX_RANGE"]

logger = logging.getLogger(__name__)

DEFAULT_ASSET = Path(__file__).resolve().parent.parent / "assets" / "headmodel" / "ict_facekit.npz"

# Meshes that are shading helpers in ICT-FaceKit, not visible surfaces: never rendered.
SHADING_HELPER_MATERIALS = ("M_LacrimalFluid", "M_EyeBlend", "M_EyeOcclusion")

# Vertex index ranges of the model's parts (ICT-FaceKit documentation), end exclusive.
HEAD_VERTEX_RANGE = (0, 11248)  # face 0-9408, head and neck 9409-11247 (the skin)
SOCKET_VERTEX_RANGE = (11248, 14062)  # mouth socket and eye sockets
TEETH_VERTEX_RANGE = (17039, 21451)
EYEBALL_VERTEX_RANGE = (21451, 24591)


def _to_numpy(x, n: int, what: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float32)
    if a.shape != (n,):
        raise ValueError(f"{what} must have shape [{n}], got {tuple(a.shape)}")
    return a


@dataclass(frozen=True, eq=False)
class HeadModel:
    """The linear head model. Arrays are numpy; lengths in metres, centred (see module doc)."""

    neutral: np.ndarray  # [Nv, 3] float32, metres
    identity_basis: np.ndarray  # [100, Nv, 3] float32, metres per unit weight
    expression_basis: np.ndarray  # [53, Nv, 3] float32, metres per unit weight
    faces: np.ndarray  # [F, 3] int32 vertex ids, counter-clockwise seen from outside
    face_uvs: np.ndarray  # [F, 3] int32 ids into uvs
    uvs: np.ndarray  # [Nuv, 2] float32
    face_material: np.ndarray  # [F] int16 ids into material_names
    material_names: tuple[str, ...]  # 12 names, M_Face ... M_EyeLashes
    expression_names: tuple[str, ...]  # 53 ict53 names, browDown_L ... noseSneer_R
    landmarks68: np.ndarray  # [68] int32 vertex ids (Multi-PIE 68-point order)
    center_cm: np.ndarray  # [3] float32, the subtracted origin, in the archive's centimetres
    license: str = field(repr=False, default="")

    # ------------------------------------------------------------------ loading
    @staticmethod
    def load(path: str | Path | None = None) -> "HeadModel":
        """The head model from ``path`` (default: the shipped asset); cached per path."""
        return _load_cached(str(Path(path).resolve()) if path is not None else str(DEFAULT_ASSET))

    # ------------------------------------------------------------------ sizes
    @property
    def num_vertices(self) -> int:
        return int(self.neutral.shape[0])

    @property
    def num_identity(self) -> int:
        return int(self.identity_basis.shape[0])

    @property
    def num_expression(self) -> int:
        return int(self.expression_basis.shape[0])

    # ------------------------------------------------------------------ geometry
    def vertices(self, identity=None, expression=None):
        """Vertices ``[Nv, 3]`` in metres for identity ``[100]`` and ``ict53`` expression ``[53]``.

        ``None`` means zeros (the generic neutral). Inputs may be numpy arrays, lists or torch
        tensors; if either is a torch tensor the result is a torch tensor (differentiable, on the
        tensor's device and dtype), otherwise a float32 numpy array.
        """
        try:
            import torch

            is_torch = isinstance(identity, torch.Tensor) or isinstance(expression, torch.Tensor)
        except ImportError:  # pragma: no cover
            is_torch = False
        if is_torch:
            return self._vertices_torch(identity, expression)
        v = self.neutral.copy()
        if identity is not None:
            w = _to_numpy(identity, self.num_identity, "identity")
            v += _blend(self.identity_basis, w)
        if expression is not None:
            w = _to_numpy(expression, self.num_expression, "expression")
            v += _blend(self.expression_basis, w)
        return v

    def _vertices_torch(self, identity, expression):
        import torch

        ref = identity if isinstance(identity, torch.Tensor) else expression
        dev, dt = ref.device, ref.dtype if ref.dtype.is_floating_point else torch.float32
        v = torch.tensor(self.neutral, device=dev, dtype=dt)
        for w, basis, n, what in (
            (identity, self.identity_basis, self.num_identity, "identity"),
            (expression, self.expression_basis, self.num_expression, "expression"),
        ):
            if w is None:
                continue
            w = torch.as_tensor(w, device=dev, dtype=dt)
            if tuple(w.shape) != (n,):
                raise ValueError(f"{what} must have shape [{n}], got {tuple(w.shape)}")
            v = v + torch.einsum("k,kvd->vd", w, torch.tensor(basis, device=dev, dtype=dt))
        return v

    def landmarks(self, vertices) -> np.ndarray:
        """The 68 landmark points ``[68, 3]`` of ``vertices [Nv, 3]``."""
        return vertices[self.landmarks68]

    # ------------------------------------------------------------------ topology helpers
    def material_id(self, name: str) -> int:
        if name not in self.material_names:
            raise ValueError(f"unknown material {name!r}; expected one of {list(self.material_names)}")
        return self.material_names.index(name)

    def material_mask(self, *names: str) -> np.ndarray:
        """``[F]`` bool: triangles whose material is one of ``names``."""
        ids = [self.material_id(n) for n in names]
        return np.isin(self.face_material, ids)

    def visible_face_mask(self, eyelashes: bool = True) -> np.ndarray:
        """``[F]`` bool: triangles of visible surfaces (no shading helpers; eyelashes optional)."""
        hidden = list(SHADING_HELPER_MATERIALS) + ([] if eyelashes else ["M_EyeLashes"])
        return ~self.material_mask(*hidden)

    def visible_faces(self, eyelashes: bool = True) -> np.ndarray:
        """``[F', 3]`` int32 triangles of visible surfaces, in the archive's order."""
        return self.faces[self.visible_face_mask(eyelashes)]

    def vertex_normals(self, vertices: np.ndarray, faces: np.ndarray | None = None) -> np.ndarray:
        """Area-weighted unit vertex normals ``[Nv, 3]`` (outward) of ``vertices [Nv, 3]``."""
        return vertex_normals(vertices, self.visible_faces() if faces is None else faces)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals ``[Nv, 3]`` for ``faces [F, 3]`` (deterministic)."""
    v = np.asarray(vertices, dtype=np.float32)
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    fn = np.cross(b - a, c - a)  # [F, 3], length = 2 x area
    n = np.zeros_like(v)
    nv = v.shape[0]
    for k in range(3):
        idx = faces[:, k]
        for d in range(3):
            n[:, d] += np.bincount(idx, weights=fn[:, d], minlength=nv).astype(np.float32)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.maximum(length, 1e-12)


def _blend(basis: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``sum_k w[k] * basis[k]`` -> ``[Nv, 3]``, in a fixed summation order (bitwise reproducible)."""
    from .meshraster import blend_basis

    return blend_basis(basis, w)


@functools.lru_cache(maxsize=2)
def _load_cached(path: str) -> HeadModel:
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"head model archive {p} does not exist (expected the shipped ict_facekit.npz)")
    logger.debug("loading head model %s", p)
    with np.load(p, allow_pickle=False) as d:
        neutral_cm = d["neutral"].astype(np.float32)
        lm = d["landmarks68"].astype(np.int32)
        head = neutral_cm[HEAD_VERTEX_RANGE[0] : HEAD_VERTEX_RANGE[1]]
        chin_y, crown_y = float(neutral_cm[lm[8], 1]), float(head[:, 1].max())
        nose_z = float(neutral_cm[lm[30], 2])
        back_z = float(head[head[:, 1] > chin_y][:, 2].min())
        center = np.array([0.0, 0.5 * (chin_y + crown_y), 0.5 * (back_z + nose_z)], dtype=np.float32)
        scale = np.float32(0.01)  # cm -> m
        model = HeadModel(
            neutral=((neutral_cm - center) * scale).astype(np.float32),
            identity_basis=(d["identity_deltas"].astype(np.float32) * scale),
            expression_basis=(d["expression_deltas"].astype(np.float32) * scale),
            faces=d["faces"].astype(np.int32),
            face_uvs=d["face_uvs"].astype(np.int32),
            uvs=d["uvs"].astype(np.float32),
            face_material=d["face_material"].astype(np.int16),
            material_names=tuple(str(s) for s in d["material_names"]),
            expression_names=tuple(str(s) for s in d["expression_names"]),
            landmarks68=lm,
            center_cm=center,
            license=str(d["license"]) if "license" in d.files else "",
        )
    for arr in (model.neutral, model.identity_basis, model.expression_basis, model.faces):
        arr.setflags(write=False)
    return model
