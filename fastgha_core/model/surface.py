"""Per-pixel ray depth from a tracked head surface: one geometry shared by every input view.

Why (issue 17, measured on the real photo sets): from a few real photos the network's per-pixel
depth disagrees between views (the decoder was trained on synthetic heads, and tracking leaves pose
errors of a few degrees), so each view's Gaussians land at a different depth and a novel view shows
two overlapping faces. The tracker (``fastgha_core.tracking``) has already fitted **one** ICT-FaceKit
head per person (shared identity, per-photo expression and pose) that projects onto each photo's
landmarks. Putting the Gaussian of every pixel on that surface, along the pixel's own ray, makes the
views agree where they overlap whatever the pose error: the fit ties each photo's eyes, nose and
mouth to the same surface points.

Per pixel of each input view (``surface_ray_depth``):

- where the ray hits the head mesh (skin, ears, eyes; ICT-FaceKit's visible surfaces without the
  eyelashes), the distance along the ray to the first hit, eroded by one pixel at the outline where
  a ray grazes the surface;
- elsewhere (hair beyond the skull, neck, shoulders, background), the distance of the nearest hit
  pixel (a Euclidean distance transform), so those Gaussians form a continuous shell around the head
  instead of a second layer at the network's guess;
- except pixels off the head, above the chin, whose nearest head pixel is on the face's midline
  (nose, lips, chin, forehead centre): in front of a profile's nose there is only air, and what a matte leaves there
  (wall, shadow) would be laid along the nose as a white streak (seen on the real sets);
  ``beyond_face`` marks them and ``FastGHA.reconstruct`` drops their Gaussians.
- by default (``GaussianHeadConfig.off_head_behind_ears``), off-head pixels beside the face between
  the chin and the brows, seen by a roughly frontal view, move back to the ears' plane by up to 15 cm
  (``off_head_behind_ears``): a frontal photo's hair beside the cheeks, placed at the cheek outline's
  distance, otherwise stands in the air in front of the mouth of side views (``docs/model-card-log.md``,
  "Hair beside the face");
- optionally (``neck``, ``GaussianHeadConfig.neck_cylinder``, off by default), pixels below the
  chin whose ray enters the tracked neck continued as a cylinder (``neck_cylinder_depth``) lie there
  instead; tried against phone-5's shoulder smears, it lowered the real-photo means and left the
  smear: that photo's neck lies on the mesh's own neck and collar, not off it (``docs/model-card-log.md``).
- optionally (``GaussianHeadConfig.off_head_hull``, off by default), the off-head pixels inside their
  view's matte move onto the visual hull of the other views' mattes (``off_head_on_hull``,
  ``hull_ray_depth``): where the ray enters it, or only where the nearest-hit placement falls
  outside it. Measured on the real photo sets, no variant raised the leave-one-out means: from a
  few photos the hull is loose, and the nearest-hit placement already lies inside it for nine in ten
  of those pixels (``docs/model-card-log.md``).

The head model is bald. ``surface_ray_depth(..., hair_m=...)`` pushes its scalp (``hair_vertex_weight``)
out along the mesh's normals by a hair thickness, which ``FastGHA.reconstruct`` chooses per avatar
from the inputs' mattes (``fit_hair_thickness``: the thickness whose head best fills the mattes
above the brows): without it, hair seen from above lies on the skull and the fringe's rays end on
the forehead, so a frontal render shows hair on the forehead and the top of the head cut off
(measured on the real photo sets, ``docs/model-card-log.md``).

Distances are along the pixel ray from the camera centre (``Cameras.pixel_rays``), in metres: the
quantity ``GaussianHead`` calls ``t``. The head frame is the tracker's: metres, +x the subject's
left, +y up, +z out of the face, origin the ICT head centre (``docs/conventions.md``), which is the
world frame of the tracked cameras (``tracking/camera.py``: ``w2c = [R | t]`` of the head pose).
``blend_network_depth`` (``FastGHA.reconstruct(..., surface_mode="blend")``) uses the surface on the
bare face only (``SurfaceDepth.face_hit``) and the network's depth elsewhere, joined to the face by a
fading offset: the head model has no hair volume, and on held-out synthetic subjects replacing the
hair's depth too lost 1.5 dB (``docs/model-card-log.md``).

Just behind an occluding edge of the head as a view sees it (the far side of the nose ridge in a
turned view) the view meets the surface at a grazing angle: each pixel's patch of skin is several
footprints long, and from the front its pixel-sized Gaussians leave gaps. Through them the back of
the head showed a dark hatched streak down the nose of frontal renders (real photo sets, issue 17).
``FastGHA.reconstruct`` can lengthen those Gaussians along the surface (``surface_steps``,
``behind_occluding_edges``, ``stretch_to_patches``; ``GaussianHeadConfig.grazing_stretch``). Since
2026-12-03 it does so wherever a view sees the head at a grazing angle except on the brows, eyes,
nose and mouth (``away_from_face_features``): a frontal photo's cheek columns left the same gaps,
seen from the side as stripes (``docs/model-card-log.md``, "The cheek stripes of side views").

Photos that come with their own cameras (held-out synthetic renders, a request's ``cameras.json``)
have a world of their own: ``tracking.pipeline.track_known_cameras`` fits the head through those
cameras and gives the surface a ``head_to_world`` transform (``tracking.fit.fit_known_cameras``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..cameras import Cameras

__all__ = [
    "HeadSurface",
    "SurfaceDepth",
    "surface_ray_depth",
    "face_vertex_mask",
    "front_face_vertex_mask",
    "blend_network_depth",
    "hair_vertex_weight",
    "fit_hair_thickness",
    "carve_into_mattes",
    "midline_reflection",
    "hair_carve_fractions",
    "surface_steps",
    "stretch_to_patches",
    "behind_occluding_edges",
    "away_from_face_features",
    "FACE_FEATURE_LANDMARKS",
    "sample_photo_colours",
    "hull_ray_depth",
    "off_head_on_hull",
    "below_chin",
    "off_head_behind_ears",
]

BESIDE_FACE_MAX_ANGLE_DEG = 45.0  # off_head_behind_ears: only rays within this angle of the head's backward axis (frontal-ish views; a side view's ray runs nearly along the ears' plane)
BESIDE_FACE_MAX_MOVE_M = 0.15  # off_head_behind_ears: pixels that would move further than this (metres) stay (hair hangs within ~15 cm behind the cheek's outline)
BESIDE_FACE_LATERAL_M = 0.06  # off_head_behind_ears: off-head points further than this from the midline (metres) count as beside the face
HAIR_CANDIDATES_M = (0.0, 0.005, 0.01, 0.015, 0.02, 0.025, 0.03)  # fit_hair_thickness' default choices (metres)


def vertex_normals(v: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``[Nv, 3]`` unit area-weighted vertex normals of the mesh ``v [Nv, 3]``, ``faces [F, 3]``
    (counter-clockwise seen from outside, so they point out; 0 for vertices of no face)."""
    v = np.asarray(v, dtype=np.float64)
    fn = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    idx = np.asarray(faces, dtype=np.int64).reshape(-1)
    n = np.stack([np.bincount(idx, np.repeat(fn[:, c], 3), minlength=len(v)) for c in range(3)], axis=1)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def hair_vertex_weight(head) -> np.ndarray:
    """``[Nv]`` in [0, 1]: how much of the hair thickness each ICT-FaceKit vertex takes. 1 on the
    scalp more than 6 cm above the brows and on the back of the head above the ears, ramping to 0
    over 3 cm towards the forehead and the ears; 0 on the face below that, the neck, the eyes and
    the mouth. The head model is bald: hair lies on top of its scalp."""
    from ..data.headmodel import HEAD_VERTEX_RANGE

    v = head.neutral
    lm = v[head.landmarks68]
    brow = lm[17:27, 1].max()
    top = np.clip((v[:, 1] - (brow + 0.03)) / 0.03, 0, 1)
    back = np.clip((lm[0, 2] - 0.02 - v[:, 2]) / 0.03, 0, 1) * np.clip((v[:, 1] - lm[0, 1]) / 0.03, 0, 1)
    w = np.maximum(top, back)
    w[HEAD_VERTEX_RANGE[1] :] = 0.0  # skin only (face, head and neck)
    return w


def _photo_frame(crop: Cameras, photo: Cameras) -> np.ndarray:
    """``[4]`` (left, top, right, bottom): the photo's image, as fractions of the crop's width and
    height, through the two cameras' intrinsics (one pose: the crop is the photo's camera cropped and
    resized, ``Cameras.crop`` / ``resize``)."""
    kc, kp = crop.flatten().K[0].double().numpy(), photo.flatten().K[0].double().numpy()
    x = (np.array([0.0, photo.width]) - kp[0, 2]) / kp[0, 0] * kc[0, 0] + kc[0, 2]
    y = (np.array([0.0, photo.height]) - kp[1, 2]) / kp[1, 1] * kc[1, 1] + kc[1, 2]
    return np.array([x[0] / crop.width, y[0] / crop.height, x[1] / crop.width, y[1] / crop.height])


@dataclass
class HeadSurface:
    """The tracked ICT-FaceKit head of one person, one expression per input view.

    Attributes:
        identity: ``[100]`` ICT identity coefficients (``FitResult.identity``; modes ~ N(0, 1)).
        expressions: ``[V, 53]`` ``ict53`` blendshape weights of each input photo, in [0, 1].
        head_to_world: ``[4, 4]`` rigid transform, ``x_world = R x_head + t`` (metres), from the
            head frame (module doc) to the world of the cameras the surface is used with; None =
            identity (the tracker's head-centric cameras). From ``tracking.fit.fit_known_cameras``
            when the photos came with their own cameras.
        frames: ``[V, 4]`` the part of each view's image that shows its photo, as ``(left, top,
            right, bottom)`` fractions of the image's width and height; the rest is the tracker's
            crop padding (``BACKGROUND_RGB``, like matted background, but nothing is known there).
            From ``tracking.TrackedPhotos`` (``from_tracking``); None = every pixel is the photo's.
            Fractions, so they hold for the view resized (``FastGHA.prepare`` resizes the square
            crops); ``padding`` gives the pixels.
    """

    identity: np.ndarray
    expressions: np.ndarray
    head_to_world: np.ndarray | None = None
    frames: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.identity = np.asarray(self.identity, dtype=np.float32).reshape(-1)
        self.expressions = np.asarray(self.expressions, dtype=np.float32)
        if self.head_to_world is not None:
            h = np.asarray(self.head_to_world, dtype=np.float64)
            if h.shape != (4, 4) or not np.isfinite(h).all():
                raise ValueError(f"HeadSurface: head_to_world must be a finite [4, 4] matrix, got shape {list(h.shape)}")
            r = h[:3, :3]
            if np.abs(r @ r.T - np.eye(3)).max() > 1e-3 or np.linalg.det(r) < 0 or np.abs(h[3] - [0, 0, 0, 1]).max() > 1e-6:
                raise ValueError("HeadSurface: head_to_world must be rigid (a rotation and a translation, last row 0 0 0 1)")
            self.head_to_world = h
        if self.expressions.ndim != 2 or self.expressions.shape[1] != 53:
            raise ValueError(f"HeadSurface: expressions must have shape [V, 53] (ict53), got {list(self.expressions.shape)}")
        if self.identity.shape[0] > 100:
            raise ValueError(f"HeadSurface: identity must have at most 100 ICT coefficients, got {self.identity.shape[0]}")
        if self.frames is not None:
            f = np.asarray(self.frames, dtype=np.float64)
            if f.shape != (self.expressions.shape[0], 4) or not np.isfinite(f).all() or (f[:, 2] <= f[:, 0]).any() or (f[:, 3] <= f[:, 1]).any():
                raise ValueError(f"HeadSurface: frames must be [V, 4] finite (left, top, right, bottom) fractions with right > left and bottom > top, one row per view, got shape {list(f.shape)}")
            self.frames = f
        if not (np.isfinite(self.identity).all() and np.isfinite(self.expressions).all()):
            raise ValueError("HeadSurface: identity and expressions must be finite")

    def __len__(self) -> int:
        return int(self.expressions.shape[0])

    @property
    def centre(self) -> torch.Tensor:
        """``float32 [3]``: the head frame's origin in world coordinates (metres): ``head_to_world``'s
        translation, or the world origin when the head frame is the world's (the tracker's)."""
        if self.head_to_world is None:
            return torch.zeros(3)
        return torch.as_tensor(np.asarray(self.head_to_world)[:3, 3], dtype=torch.float32)

    @staticmethod
    def from_tracking(tracked) -> "HeadSurface":
        """From ``tracking.TrackedPhotos`` (with the crops' ``frames``, from each crop's camera and its
        photo's) or a ``tracking.fit.FitResult`` (without)."""
        fit = getattr(tracked, "fit", tracked)
        frames = None
        photo_cams = getattr(tracked, "photo_cameras", None)
        if photo_cams is not None and getattr(tracked, "cameras", None) is not None:
            crops = tracked.cameras.flatten()
            frames = np.stack([_photo_frame(crops[i], photo_cams[i] if isinstance(photo_cams, list) else photo_cams.flatten()[i]) for i in range(len(crops.K))])
        return HeadSurface(fit.identity, fit.expressions, getattr(fit, "head_to_world", None), frames)

    def subset(self, views) -> "HeadSurface":
        """The surface of the views ``views`` (indices or a bool mask), in that order."""
        idx = np.asarray(views)
        return HeadSurface(self.identity, self.expressions[idx], self.head_to_world, None if self.frames is None else self.frames[idx])

    def padding(self, width: int, height: int) -> Tensor:
        """``bool [V, height, width]``: the pixels of each view, at that size, outside its photo's
        frame (``frames``; all False without frames)."""
        out = torch.zeros(len(self), height, width, dtype=torch.bool)
        if self.frames is None:
            return out
        u = (torch.arange(width, dtype=torch.float64) + 0.5) / width
        r = (torch.arange(height, dtype=torch.float64) + 0.5) / height
        for i, (l, t, rr, b) in enumerate(self.frames):
            out[i] = ~(((r >= t) & (r < b))[:, None] & ((u >= l) & (u < rr))[None, :])
        return out

    def vertices(self, view: int, head=None) -> np.ndarray:
        """World vertices ``[Nv, 3]`` (metres) of view ``view``'s expression: the head frame moved by
        ``head_to_world`` (when set)."""
        from ..data.headmodel import HeadModel

        head = head or HeadModel.load()
        ident = np.zeros(head.num_identity, np.float32)
        ident[: len(self.identity)] = self.identity[: head.num_identity]
        v = head.vertices(ident, self.expressions[view])
        if self.head_to_world is not None:
            h = self.head_to_world
            v = (v.astype(np.float64) @ h[:3, :3].T + h[:3, 3]).astype(np.float32)
        return v

    def points(self, vertex_ids, head=None) -> np.ndarray:
        """World positions ``[V, K, 3]`` (metres) of the head model's vertices ``vertex_ids [K]`` in every
        view's expression: ``vertices(view)[vertex_ids]`` for each view, blended for those vertices only."""
        from ..data.headmodel import HeadModel

        head = head or HeadModel.load()
        ids = np.asarray(vertex_ids, dtype=np.int64)
        ident = np.zeros(head.num_identity, np.float32)
        ident[: len(self.identity)] = self.identity[: head.num_identity]
        base = head.neutral[ids].astype(np.float64) + np.einsum("k,kij->ij", ident.astype(np.float64), head.identity_basis[:, ids])
        p = base[None] + np.einsum("vk,kij->vij", self.expressions.astype(np.float64), head.expression_basis[:, ids])
        if self.head_to_world is not None:
            h = self.head_to_world
            p = p @ h[:3, :3].T + h[:3, 3]
        return p.astype(np.float32)

    def head_fit(self, basis, hair_m=0.0):
        """The ``model.prior.HeadFit`` of this head at the neutral expression (identity truncated to
        the basis' modes), so the expression prior binds to the tracked surface instead of an ICP fit.

        ``hair_m`` (metres, >= 0; a float or ``[Nv]`` per vertex): the scalp pushed out along the bald mesh's outward normals by this
        hair thickness (``hair_vertex_weight``, as ``surface_ray_depth`` lays it out for the pixels), so
        that what is built on the fit -- the back-of-head shell (``prior.back_shell``), the binding --
        sits on the hair the reconstructed Gaussians lie on, not on the bald skull under it
        (``FastGHA.reconstruct`` uses it for the shell only; the binding stays on the bald head). Needs an
        ICT-FaceKit basis (the same vertices as ``HeadModel``); raises ``ValueError`` otherwise."""
        from .prior import HeadFit

        k = basis.identity_basis.shape[0]
        ident = np.zeros(k, np.float32)
        n = min(k, len(self.identity))
        ident[:n] = self.identity[:n]
        verts = basis.neutral.astype(np.float64) + np.tensordot(ident, basis.identity_basis, axes=1)
        h = np.eye(4) if self.head_to_world is None else self.head_to_world
        verts = verts @ h[:3, :3].T + h[:3, 3]
        if np.any(np.asarray(hair_m) > 0):
            from ..data.headmodel import HeadModel

            head = HeadModel.load()
            if verts.shape[0] != head.num_vertices:
                raise ValueError(f"head_fit: hair_m needs an ICT-FaceKit basis of {head.num_vertices} vertices, got {verts.shape[0]}")
            nrm = vertex_normals(verts, head.visible_faces(eyelashes=False))
            verts = verts + np.asarray(hair_m, dtype=np.float64)[..., None] * hair_vertex_weight(head)[:, None] * nrm
        return HeadFit(identity=ident, transform=h.astype(np.float32), vertices=verts.astype(np.float32), rms=0.0)


@dataclass
class SurfaceDepth:
    """Per-pixel geometry of ``V`` input views from the tracked head (module doc)."""

    t: Tensor  # [V, H, W] float32 metres along each pixel's unit ray
    hit: Tensor  # [V, H, W] bool: the pixel's own ray hits the head
    beyond_face: Tensor  # [V, H, W] bool: off the head, next to the face's outline (air: no Gaussian)
    face_hit: Tensor | None = None  # [V, H, W] bool: hit pixels on the bare face (front_face_vertex_mask)

    def off_head(self, foreground: Tensor) -> Tensor:
        """``bool [V, H, W]`` (CPU): the off-head pixels, those inside their view's matte
        (``foreground [V, H, W] > 0.5``) whose ray misses the head and that are not ``beyond_face``:
        ``surface_ray_depth`` gives them the nearest head pixel's distance (``off_head_on_hull``,
        ``off_head_draw_flags``)."""
        return ~self.hit.cpu() & ~self.beyond_face.cpu() & (foreground.detach().float().cpu() > 0.5)


def front_face_vertex_mask(head) -> np.ndarray:
    """``[Nv]`` bool: ICT-FaceKit face-mesh vertices of the bare face: in front of the jaw-line's first
    landmark (``z``) and below the brows + 3 cm, so hair, ears and the scalp (whose visible surface
    is the hair above it, not the skull) are left out."""
    v = head.neutral
    lm = v[head.landmarks68]
    m = np.zeros(len(v), bool)
    m[:9409] = True  # the face mesh (data/headmodel.py: face 0-9408)
    return m & (v[:, 2] > lm[0, 2]) & (v[:, 1] < lm[17:27, 1].max() + 0.03)


def blend_network_depth(sd: SurfaceDepth, t_net: Tensor, falloff_px: float = 8.0) -> Tensor:
    """The network's ray depth ``t_net [V, H, W]`` (metres) moved onto the head surface on the face.

    On the bare face (``sd.face_hit``) the surface's distance; elsewhere the network's, shifted by
    the surface-minus-network difference of the nearest bare-face pixel (smoothed over 2 pixels),
    fading as ``exp(-d / falloff)`` with the distance ``d`` to the face (``falloff_px`` pixels at a
    side of 256, scaled with the image). So the face, where views must agree exactly (eyes, nose,
    mouth), lies on the one fitted head and joins the rest without a step, while hair, ears and
    shoulders keep the network's depth (the head model has no hair volume; moving them with the
    face lowered held-out PSNR by 1.5 dB, docs/model-card-log.md). Views without a bare-face pixel keep
    the network's depth. ``falloff_px <= 0``: no fading (the whole view shifted).
    """
    from scipy.ndimage import distance_transform_edt, gaussian_filter

    if sd.face_hit is None:
        raise ValueError("blend_network_depth: the SurfaceDepth has no face_hit mask")
    tn = t_net.detach().float().cpu().numpy()
    ts, fh = sd.t.numpy(), sd.face_hit.numpy()
    if tn.shape != ts.shape:
        raise ValueError(f"blend_network_depth: t_net must have shape {list(ts.shape)}, got {list(tn.shape)}")
    fall = float(falloff_px)
    out = tn.copy()
    for i in range(len(ts)):
        if not fh[i].any():
            continue
        dist, (iy, ix) = distance_transform_edt(~fh[i], return_indices=True)
        off = gaussian_filter((ts[i] - tn[i])[iy, ix], 2.0)
        if fall > 0:
            off = off * np.exp(-dist / (fall * ts.shape[-1] / 256.0))
        out[i] = np.where(fh[i], ts[i], tn[i] + off)
    return torch.from_numpy(out).to(t_net)


def face_vertex_mask(head) -> np.ndarray:
    """``[Nv]`` bool: ICT-FaceKit vertices of the face's midline strip (``|x| < 2.5 cm`` of the face
    mesh, below the brows + 2 cm: forehead centre, nose, lips, chin). Off the head next to them there
    is only air in every view (a profile's nose, a raised chin); beside the cheeks and temples hair,
    ears and shoulders continue the head, so those stay."""
    v = head.neutral
    lm = v[head.landmarks68]
    m = np.zeros(len(v), bool)
    m[:9409] = True  # the face mesh (data/headmodel.py: face 0-9408)
    m &= (np.abs(v[:, 0]) < 0.025) & (v[:, 2] > lm[0, 2]) & (v[:, 1] < lm[17:27, 1].max() + 0.02)
    return m


def _hair_offsets(surface: HeadSurface, i: int, head, faces) -> tuple[np.ndarray, np.ndarray]:
    """View ``i``'s world vertices ``[Nv, 3]`` and each vertex's hair direction scaled by its
    ``hair_vertex_weight`` ``[Nv, 3]`` (outward normals of the bald mesh)."""
    vw = surface.vertices(i, head).astype(np.float64)
    return vw, hair_vertex_weight(head)[:, None] * vertex_normals(vw, faces)


def _view_mesh(surface: HeadSurface, i: int, head, faces, hair_m) -> np.ndarray:
    """World vertices of view ``i``, the scalp pushed out along its normals by ``hair_m`` metres
    (one thickness, or ``[Nv]`` per vertex: ``hair_carve_fractions``)."""
    if np.all(np.asarray(hair_m) <= 0):
        return surface.vertices(i, head).astype(np.float64)
    vw, off = _hair_offsets(surface, i, head, faces)
    return vw + np.asarray(hair_m, dtype=np.float64)[..., None] * off


def fit_hair_thickness(surface: HeadSurface, cameras: Cameras, masks: Tensor, candidates=HAIR_CANDIDATES_M) -> float:
    """The hair thickness (metres, one of ``candidates``) whose head best fills the inputs' mattes
    above the brows.

    The tracked head is bald, so from a frontal camera the hair's top outline lies above it and
    hair seen from above lands on the scalp, below the hair's surface (in a novel view: a band
    missing along the top of the head, hair on the forehead). For each candidate the scalp
    (``hair_vertex_weight``) is pushed out along its normals and rasterised at every input camera;
    the score is the intersection over union of the head's coverage and the matte, over the rows
    above the view's highest brow landmark, summed over views; the best candidate is returned
    (ties: the thinner). Long hair that falls beside the face is outside any thickness and
    lowers every candidate alike.

    Args:
        surface: ``V`` views of one tracked head.
        cameras: ``Cameras [V]`` of the ``W x H`` input views (world = the head frame).
        masks: ``[V, H, W]`` the inputs' mattes (> 0.5 = the person).
        candidates: thicknesses to try, metres, each >= 0.
    Raises:
        ValueError: when the sizes disagree or a candidate is negative.
    """
    from ..data.headmodel import HeadModel
    from ..data.meshraster import render_mesh

    cams = cameras.flatten()
    v, w, h = len(cams.K), cams.width, cams.height
    if v != len(surface) or tuple(masks.shape) != (v, h, w):
        raise ValueError(f"fit_hair_thickness: expected {len(surface)} cameras and masks [{len(surface)}, {h}, {w}], got {v} and {list(masks.shape)}")
    cand = [float(c) for c in candidates]
    if not cand or min(cand) < 0:
        raise ValueError(f"fit_hair_thickness: candidates must be a non-empty list of thicknesses >= 0, got {cand}")
    head = HeadModel.load()
    faces = head.visible_faces(eyelashes=False)
    ones = np.ones((head.num_vertices, 1), np.float32)
    mk = masks.detach().cpu().numpy() > 0.5
    pad = surface.padding(w, h).numpy()  # the crop's padding: neither the person nor background
    rows = np.arange(h)[:, None]
    scores = np.zeros(len(cand))
    for i in range(v):
        w2c = cams.w2c[i].double().numpy()
        K = cams.K[i].double().numpy()
        vw, off = _hair_offsets(surface, i, head, faces)
        for j, c in enumerate(cand):
            pts = (vw + c * off) @ w2c[:3, :3].T + w2c[:3, 3]
            if j == 0:
                brow = pts[head.landmarks68[17:27]]
                top = (rows < float((K[1, 1] * brow[:, 1] / brow[:, 2] + K[1, 2]).min())) & ~pad[i]
            cov = render_mesh(pts.astype(np.float32), faces, ones, K, w, h, supersample=1).alpha > 0.5
            union = ((cov | mk[i]) & top).sum()
            scores[j] += ((cov & mk[i]) & top).sum() / union if union else 0.0
    return cand[int(np.argmax(scores))]  # argmax takes the first of equal scores; candidates sorted by the caller


NECK_RING_Y_M = (-0.15, -0.12)  # head-frame heights (metres) of the ICT neck vertices the neck cylinder is fitted to


def neck_ring_vertices(head) -> np.ndarray:
    """Indices of the ICT-FaceKit skin vertices of the neck between ``NECK_RING_Y_M`` (head frame,
    neutral identity): 2-5 cm below the chin (chin landmark at y = -0.11 m), above the collar where
    the mesh flares into the shoulders (y < -0.16 m)."""
    from ..data.headmodel import HEAD_VERTEX_RANGE

    y = head.neutral[: HEAD_VERTEX_RANGE[1], 1]
    return np.nonzero((y >= NECK_RING_Y_M[0]) & (y <= NECK_RING_Y_M[1]))[0]


def neck_cylinder_depth(pts_cam: np.ndarray, ring: np.ndarray, up_cam: np.ndarray, chin_cam: np.ndarray, K: np.ndarray, w: int, h: int) -> np.ndarray:
    """Distance along each pixel's unit ray (metres) to where it enters the neck cylinder, below the chin.

    The neck is taken as an infinite cylinder along the head's up axis through the neck ring's
    vertices (centre their mean, radius the median of their distances from the axis). A pixel gets
    the distance to its ray's first crossing of it when the ray crosses it in front of the camera at a
    point lower than the chin (along the up axis); NaN otherwise.

    Args:
        pts_cam: ``[Nv, 3]`` the view's head vertices in camera coordinates (OpenCV: +z forward).
        ring: vertex indices of the neck ring (``neck_ring_vertices``).
        up_cam: ``[3]`` the head's +y axis in camera coordinates (unit).
        chin_cam: ``[3]`` the chin landmark in camera coordinates.
        K: ``[3, 3]`` intrinsics; ``w``, ``h``: image size in pixels.
    Returns:
        ``[h, w]`` float64 distances, NaN where the ray misses the neck or enters it above the chin.
    """
    a = up_cam / np.linalg.norm(up_cam)
    ring_pts = pts_cam[ring].astype(np.float64)
    c = ring_pts.mean(0)
    off = ring_pts - c
    rho = float(np.median(np.linalg.norm(off - (off @ a)[:, None] * a, axis=1)))
    u, r = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    d = np.stack([(u - K[0, 2]) / K[0, 0], (r - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    dp = d - (d @ a)[..., None] * a
    cp = c - (c @ a) * a
    A = (dp * dp).sum(-1)
    B = dp @ cp
    C = float(cp @ cp) - rho * rho
    disc = B * B - A * C
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (B - np.sqrt(disc)) / A
    ok = (disc > 0) & (A > 1e-12) & (t > 0)
    below = ((t[..., None] * d - chin_cam) @ a) < 0
    return np.where(ok & below, t, np.nan)


def surface_ray_depth(surface: HeadSurface, cameras: Cameras, hair_m=0.0, neck: str = "off") -> SurfaceDepth:
    """Ray distances (metres) to the tracked head for every pixel of ``cameras``.

    Args:
        surface: ``V`` views of one tracked head.
        cameras: ``Cameras [V]`` of the ``W x H`` input views (world = the head frame).
        hair_m: hair thickness (metres): the scalp is pushed out along its normals by this much
            (``hair_vertex_weight``; ``fit_hair_thickness`` chooses it from the inputs' mattes); a
            float, or ``[Nv]`` per ICT-FaceKit vertex (``hair_carve_fractions`` x the fitted one).
        neck: ``"off"``; ``"off_head"``: off-head pixels whose ray enters the neck cylinder
            (``neck_cylinder_depth``: the tracked neck ring continued along the head's up axis) below
            the chin take that distance instead of the nearest hit pixel's; ``"below_ring"``: so do
            the pixels hitting the mesh below the neck ring (ICT's collar, which flares out towards
            the shoulders) (``GaussianHeadConfig.neck_cylinder``; docs/model-card-log.md).
    Returns:
        ``SurfaceDepth``: ``t [V, H, W]`` (hit pixels get their own ray's distance, the others the
        nearest hit pixel's), ``hit`` and ``beyond_face`` (module doc).
    Raises:
        ValueError: when the batch sizes differ, or the head is not in front of a view's camera.
    """
    from scipy.ndimage import binary_erosion, distance_transform_edt

    from ..data.headmodel import HeadModel
    from ..data.meshraster import render_mesh

    if neck not in ("off", "off_head", "below_ring"):
        raise ValueError(f"surface_ray_depth: neck must be 'off', 'off_head' or 'below_ring', got {neck!r}")
    cams = cameras.flatten()
    v = len(cams.K)
    if v != len(surface):
        raise ValueError(f"surface_ray_depth: {len(surface)} surface views but {v} cameras")
    head = HeadModel.load()
    faces = head.visible_faces(eyelashes=False)
    attrs = np.stack([np.ones(head.num_vertices), face_vertex_mask(head), front_face_vertex_mask(head)], axis=1).astype(np.float32)
    w, h = cams.width, cams.height
    u, r = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    out = np.empty((v, h, w), np.float32)
    hits = np.empty((v, h, w), bool)
    beyond = np.empty((v, h, w), bool)
    front = np.empty((v, h, w), bool)
    for i in range(v):
        w2c = cams.w2c[i].double().numpy()
        K = cams.K[i].double().numpy()
        pts = _view_mesh(surface, i, head, faces, hair_m) @ w2c[:3, :3].T + w2c[:3, 3]
        m = render_mesh(pts.astype(np.float32), faces, attrs, K, w, h, supersample=1)
        covered = (m.alpha > 0.99) & (m.depth > 0)
        hit = binary_erosion(covered, iterations=1)
        if not hit.any():
            raise ValueError(f"surface_ray_depth: the tracked head is not visible in view {i}")
        x, y = (u - K[0, 2]) / K[0, 0], (r - K[1, 2]) / K[1, 1]
        t = m.depth * np.sqrt(x * x + y * y + 1.0)  # camera z -> distance along the unit ray
        dist, (iy, ix) = distance_transform_edt(~hit, return_indices=True)
        out[i] = t[iy, ix]
        if neck != "off":
            up = np.array([0.0, 1.0, 0.0]) if surface.head_to_world is None else surface.head_to_world[:3, 1]
            up_cam = w2c[:3, :3] @ up
            tn = neck_cylinder_depth(pts, neck_ring_vertices(head), up_cam, pts[head.landmarks68[8]], K, w, h)
            take = ~hit
            if neck == "below_ring":  # also the mesh's own pixels below the neck ring (its collar)
                d = np.stack([x, y, np.ones_like(x)], -1)
                p_hit = t[..., None] * d / np.linalg.norm(d, axis=-1, keepdims=True)
                ring_low = float((pts[neck_ring_vertices(head)].astype(np.float64) @ up_cam).min())
                take = take | (hit & (p_hit @ up_cam < ring_low))
            take = take & np.isfinite(tn)
            out[i][take] = tn[take]
        hits[i] = hit
        face = m.color[..., 1] > 0.5  # premultiplied by coverage: > 0.5 only on covered face pixels
        chin = pts[head.landmarks68[8]]  # below the chin the neck and chest continue the head
        chin_row = float(K[1, 1] * chin[1] / chin[2] + K[1, 2])
        beyond[i] = ~covered & (dist > 1.5) & face[iy, ix] & (r < chin_row)
        front[i] = hit & (m.color[..., 2] > 0.5)
    return SurfaceDepth(torch.from_numpy(out), torch.from_numpy(hits), torch.from_numpy(beyond), torch.from_numpy(front))


def _per_pixel_of(cameras: Cameras, t: Tensor, who: str) -> Cameras:
    """``cameras`` flattened, after checking that ``t`` is ``[V, H, W]``: one value per pixel of each view.

    Raises:
        ValueError: naming ``who`` when ``t`` has another shape.
    """
    cams = cameras.flatten()
    v, h, w = len(cams.K), cams.height, cams.width
    if tuple(t.shape) != (v, h, w):
        raise ValueError(f"{who}: t must have shape [{v}, {h}, {w}], got {list(t.shape)}")
    return cams


def surface_steps(t: Tensor, cameras: Cameras, jump: float = 6.0) -> tuple[Tensor, Tensor]:
    """Each pixel's patch of the surface its Gaussian sits on: the steps to its neighbours' points.

    Args:
        t: ``[V, H, W]`` distances along each pixel's unit ray (metres), e.g. ``SurfaceDepth.t``.
        cameras: ``Cameras [V]`` of the ``W x H`` views (``Cameras.pixel_rays``).
        jump: a neighbour whose point is more than ``jump`` footprints away is across an occluding
            edge (e.g. behind the nose ridge) and does not count.
    Returns:
        ``(steps [V, H, W, 2, 3], footprint [V, H, W])``: world vectors (metres) from the point of
        pixel ``x - 1/2`` to that of ``x + 1/2`` (central difference, one-sided next to an edge,
        zero without a neighbour), and ``y`` likewise; and the pixel's footprint at its distance
        (``t / f``, metres). Where the ray meets the surface at incidence ``theta``, the step along
        the slope is about ``footprint / cos(theta)``.
    Raises:
        ValueError: when ``t`` is not ``[V, H, W]`` of the cameras' batch and size.
    """
    cams = _per_pixel_of(cameras, t, "surface_steps")
    o, d = cams.to(t.device, torch.float32).pixel_rays()
    p = o + t.float()[..., None] * d  # [V, H, W, 3]
    foot = t.float() / cams.K[:, 0, 0].to(t.device, torch.float32)[:, None, None]
    steps = []
    for dim in (2, 1):  # x, then y
        fwd = torch.diff(p, dim=dim, append=p.narrow(dim, p.shape[dim] - 1, 1))  # p[i+1] - p[i]
        bwd = torch.diff(p, dim=dim, prepend=p.narrow(dim, 0, 1))  # p[i] - p[i-1]
        ok_f = (fwd.norm(dim=-1) <= jump * foot) & (fwd.norm(dim=-1) > 0)
        ok_b = (bwd.norm(dim=-1) <= jump * foot) & (bwd.norm(dim=-1) > 0)
        n = (ok_f.float() + ok_b.float()).clamp_min(1)[..., None]
        steps.append((fwd * ok_f[..., None] + bwd * ok_b[..., None]) / n)
    return torch.stack(steps, dim=-2), foot


def stretch_to_patches(g, steps: Tensor, footprint: Tensor, sigma_per_step: float = 0.5, min_ratio: float = 1.5, where: Tensor | None = None):
    """Lengthen pixel-aligned Gaussians along the surface where their pixel's patch is longer than
    its footprint (the view sees the surface at a grazing angle).

    Why (issue 17, measured on video-6): the nose's far flank, which every input view sees only at
    a grazing angle just behind the nose ridge, gets a few columns of Gaussians the size of a pixel
    footprint; a frontal camera sees them spread over the flank with gaps between them, and through
    the gaps the back-of-head shell's dark hair (``model.prior.back_shell``) drew a dark hatched
    streak down the nose. Each Gaussian's covariance gets, for each image axis whose step ``s`` is
    longer than ``min_ratio`` footprints ``f``, ``sigma_per_step**2 (|s|**2 - f**2)`` more variance
    along ``s``: it then covers its own patch of skin. Steps lie nearly along the ray at grazing
    angles, so the view's own image barely changes; a pixel seen head-on (``|s| ~ f``) is untouched.

    Args:
        g: ``V * H * W`` Gaussians, view-major (``FastGHA.forward_gaussians``' layout).
        steps, footprint: ``surface_steps`` of the same views.
        sigma_per_step: standard deviation added per metre of patch length beyond the footprint.
        min_ratio: patches at most this many footprints long are left as they are.
        where: optional ``[V, H, W]`` bool, the only pixels whose Gaussians may change (e.g.
            ``behind_occluding_edges``).
    Returns:
        The Gaussians with new ``scales`` and ``quats`` (same order and count).
    Raises:
        ValueError: when the counts disagree.
    """
    from ..render.projection import quat_to_rotmat
    from .gaussian_head import matrix_to_quaternion

    if len(g) != footprint.numel() or tuple(steps.shape) != (*footprint.shape, 2, 3):
        raise ValueError(f"stretch_to_patches: expected {footprint.numel()} Gaussians and steps {[*footprint.shape, 2, 3]}, got {len(g)} and {list(steps.shape)}")
    s = steps.reshape(-1, 2, 3).to(g.means)
    f = footprint.reshape(-1, 1).to(g.means)
    ln = s.norm(dim=-1)  # [N, 2]
    extra = torch.where(ln > min_ratio * f, sigma_per_step**2 * (ln**2 - f**2), torch.zeros_like(ln))  # [N, 2] variance
    sel = (extra > 0).any(-1)
    if where is not None:
        if tuple(where.shape) != tuple(footprint.shape):
            raise ValueError(f"stretch_to_patches: where must have shape {list(footprint.shape)}, got {list(where.shape)}")
        sel &= where.reshape(-1).to(sel.device)
    if not bool(sel.any()):
        return g
    u = s[sel] / ln[sel].clamp_min(1e-12)[..., None]  # [M, 2, 3]
    R = quat_to_rotmat(g.quats[sel])
    cov = R @ torch.diag_embed(g.scales[sel] ** 2) @ R.transpose(-1, -2)
    cov = cov + torch.einsum("mk,mki,mkj->mij", extra[sel], u, u)
    ev, vec = torch.linalg.eigh(cov.double())
    vec = torch.where(torch.linalg.det(vec)[:, None, None] < 0, vec * torch.tensor([-1.0, 1.0, 1.0], dtype=vec.dtype), vec)
    scales, quats = g.scales.clone(), g.quats.clone()
    scales[sel] = ev.clamp_min(1e-14).sqrt().to(scales)
    quats[sel] = matrix_to_quaternion(vec).to(quats)
    return g.replace(scales=scales, quats=quats)


def behind_occluding_edges(t: Tensor, cameras: Cameras, radius_px: int = 3, jump: float = 6.0) -> Tensor:
    """``[V, H, W]`` bool: pixels within ``radius_px`` behind an occluding edge of the surface.

    A pixel is behind an edge when a pixel within ``radius_px`` (a square window) is nearer the
    camera by more than ``jump`` of its footprints (``t / f``): the far side of the nose ridge, of
    the jaw seen from below, of an ear. There a view sees the surface at a grazing angle, and a
    tracking error of a few millimetres moves what the photo shows there (the far eye's corner, the
    nose's shaded flank) across it. Pixels off the head take a hit pixel's distance
    (``surface_ray_depth``), so a head's outline against the background is not an edge.

    Raises:
        ValueError: when ``t`` is not ``[V, H, W]`` of the cameras' batch and size.
    """
    cams = _per_pixel_of(cameras, t, "behind_occluding_edges")
    t = t.float()
    tmin = -torch.nn.functional.max_pool2d(-t[:, None], 2 * radius_px + 1, stride=1, padding=radius_px)[:, 0]
    foot = t / cams.K[:, 0, 0].to(t.device, torch.float32)[:, None, None]
    return (t - tmin) > jump * foot


FACE_FEATURE_LANDMARKS = tuple(range(17, 68))  # Multi-PIE 68-point ids of the brows, nose, eyes and mouth (not the jaw line, 0-16)


def away_from_face_features(t: Tensor, cameras: Cameras, surface: "HeadSurface", radius_m: float, head=None) -> Tensor:
    """``[V, H, W]`` bool: pixels whose surface point lies more than ``radius_m`` from every brow, nose,
    eye and mouth landmark of the tracked head (``FACE_FEATURE_LANDMARKS``, in each of the surface's
    expressions).

    Why (issue 17, the real sets' side views, ``docs/model-card-log.md`` "The cheek stripes of side
    views"): lengthening grazing pixels' Gaussians along the surface (``stretch_to_patches``) closes
    the gaps between a frontal photo's pixel columns on the cheek and the side of the head, which a
    side view showed as stripes; on the features themselves it blurred what identity rests on (the
    eye corners stayed open when the lids closed, the nose tip smeared forward in profiles). The
    landmarks are the ICT-FaceKit head's 68 points (``data/headmodel.py``), moved by the surface's
    ``head_to_world``; mirrored virtual views (``model/mirror.py``) share the head frame, and the
    features are the same on both sides of it.

    Args:
        t: ``[V, H, W]`` metres along each pixel's unit ray (``SurfaceDepth.t``).
        cameras: ``Cameras`` of ``V`` views of size ``W x H``.
        surface: the tracked ``HeadSurface`` (any number of expressions >= 1).
        radius_m: metres (> 0).
        head: the ``HeadModel`` (default: the shipped one).
    Raises:
        ValueError: when ``t`` is not ``[V, H, W]`` of the cameras' batch and size, or ``radius_m <= 0``.
    """
    from ..data.headmodel import HeadModel

    cams = _per_pixel_of(cameras, t, "away_from_face_features")
    if not radius_m > 0:
        raise ValueError(f"away_from_face_features: radius_m must be > 0, got {radius_m}")
    head = head or HeadModel.load()
    lm = torch.as_tensor(surface.points(head.landmarks68[list(FACE_FEATURE_LANDMARKS)], head)).reshape(-1, 3).to(t.device, torch.float32)
    o, d = cams.pixel_rays()
    pts = (o.to(t.device, torch.float32) + d.to(t.device, torch.float32) * t.float()[..., None]).reshape(-1, 3)
    return (torch.cdist(pts, lm).amin(1) > radius_m).reshape(t.shape)


def sample_photo_colours(points: Tensor, cameras: Cameras, photos: Tensor, view_index: Tensor) -> Tensor:
    """Each point's colour in its own source photo: bilinear at the point's projection.

    Why (issue 17, measured on the real photo sets, ``docs/model-card-log.md``): the tiny model's
    Gaussians take their colour from the 128-pixel input (``rgb_residual``: the input pixel's logit
    plus the network's residual). Sampling the photo at a higher resolution where each Gaussian
    projects is the oracle that asks how much of the leave-one-out blur is colour resolution.

    Args:
        points: ``[N, 3]`` world points (metres), e.g. ``Gaussians.means``.
        cameras: ``Cameras [V]`` of the ``W x H`` photos (any size: not tied to the model's input).
        photos: ``[V, 3, H, W]`` colours (any range; bilinear interpolation of pixel centres, pixel
            ``(x, y)``'s centre at ``(x + 0.5, y + 0.5)``, the corner convention of ``Cameras.project``).
        view_index: ``[N]`` long, the photo each point samples.
    Returns:
        ``[N, 3]`` colours; projections outside a photo take its nearest border pixel's colour.
    Raises:
        ValueError: when the shapes or the index disagree.
    """
    cams = cameras.flatten()
    v, h, w = len(cams.K), cams.height, cams.width
    if photos.ndim != 4 or tuple(photos.shape) != (v, 3, h, w):
        raise ValueError(f"sample_photo_colours: photos must have shape [{v}, 3, {h}, {w}], got {list(photos.shape)}")
    if points.ndim != 2 or points.shape[1] != 3 or tuple(view_index.shape) != (points.shape[0],):
        raise ValueError(f"sample_photo_colours: expected points [N, 3] and view_index [N], got {list(points.shape)} and {list(view_index.shape)}")
    if len(view_index) and (int(view_index.min()) < 0 or int(view_index.max()) >= v):
        raise ValueError(f"sample_photo_colours: view_index must lie in [0, {v}), got [{int(view_index.min())}, {int(view_index.max())}]")
    out = torch.empty(points.shape[0], 3, dtype=photos.dtype, device=photos.device)
    for i in range(v):
        sel = view_index == i
        if not bool(sel.any()):
            continue
        uv, _ = cams[i].to(points.device, points.dtype).project(points[sel])
        grid = torch.stack([uv[:, 0] / w * 2 - 1, uv[:, 1] / h * 2 - 1], -1).to(photos.dtype)
        col = torch.nn.functional.grid_sample(photos[i : i + 1], grid[None, None], mode="bilinear", padding_mode="border", align_corners=False)
        out[sel] = col[0, :, 0].T
    return out


PHOTO_SHAPES_MODES = ("off", "colour_opacity", "colour_opacity_scale")  # GaussianHeadConfig.photo_shapes (= config.PHOTO_SHAPES_MODES)
PHOTO_SHAPES_SCALE = 0.75  # photo_pixel_shapes' "colour_opacity_scale": every Gaussian's scales x this


def photo_pixel_shapes(g, images: Tensor, mode: str, scale: float = PHOTO_SHAPES_SCALE):
    """The input pixels' Gaussians ``g`` with their colour, opacity and (optionally) size taken from
    the photo instead of the decoder (``GaussianHeadConfig.photo_shapes``).

    Why (issue 17, ``docs/model-card-log.md`` "Where a photo's own avatar loses identity"): on a tracked
    head surface each pixel's Gaussian already lies on its own pixel, and the single-view
    decomposition found that the decoder's colour residual, its sub-1 opacities on the matte and its
    scales (up to 16 pixel footprints) soften a photo's own avatar at its own camera; all three
    together (pure input colour, opacity 1 on the matte, scales x 0.75) lowered the dlib identity
    distance 0.376 -> 0.320, each alone little. Off by default: in real-photo leave-one-out (with the
    anchored residual) "colour_opacity_scale" lowers mean identity 0.512 -> 0.498 but costs phone-5 /
    studio-4 0.13 / 0.28 dB and shows the 128² grid of smaller splats as a stipple at novel cameras
    (docs/model-card-log.md "The Gaussians' shapes on real photos, and expression-aware blending, after the anchor").

    Args:
        g: ``Gaussians`` of ``V*H*W`` points, view-major (``FastGHA.forward_gaussians``' order).
        images: ``[V, 3, H, W]`` the inputs the Gaussians came from, in [0, 1], matted on ``BACKGROUND_RGB``.
        mode: ``"off"`` (``g`` returned as is), ``"colour_opacity"`` (colour = the input pixel,
            clamped to [0.01, 0.99] as ``rgb_residual`` clamps it, i.e. that residual set to 0;
            opacity 1 where ``foreground_weight > 0.5``, elsewhere unchanged), ``"colour_opacity_scale"``
            (also every Gaussian's three scales x ``scale``).
        scale: the factor of ``"colour_opacity_scale"``, > 0.
    Returns:
        ``Gaussians`` of the same length; means, rotations and features unchanged.
    Raises:
        ValueError: on an unknown mode, a scale that is not a finite number > 0, or images whose
            pixel count is not ``len(g)``.
    """
    import math

    from .gaussian_head import foreground_weight

    if mode not in PHOTO_SHAPES_MODES:
        raise ValueError(f"photo_pixel_shapes: mode must be one of {list(PHOTO_SHAPES_MODES)}, got {mode!r}")
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not math.isfinite(scale) or scale <= 0:
        raise ValueError(f"photo_pixel_shapes: scale must be a finite number > 0, got {scale!r}")
    if mode == "off":
        return g
    if images.ndim != 4 or images.shape[1] != 3 or images.shape[0] * images.shape[2] * images.shape[3] != len(g):
        raise ValueError(f"photo_pixel_shapes: images must be [V, 3, H, W] with V*H*W = {len(g)} pixels, got {list(images.shape)}")
    img = images.to(g.colors.device, torch.float32)
    colors = img.clamp(0.01, 0.99).permute(0, 2, 3, 1).reshape(-1, 3).to(g.colors.dtype)
    fg = foreground_weight(img).reshape(-1) > 0.5
    opac = torch.where(fg, torch.ones_like(g.opacities), g.opacities)
    out = g.replace(colors=colors, opacities=opac)
    if mode == "colour_opacity_scale":
        out = out.replace(scales=g.scales * scale)
    return out



def _mattes(foreground: Tensor, dilate_px: int) -> Tensor:
    """``bool [V, H, W]``: ``foreground [V, H, W] > 0.5``, dilated by ``dilate_px`` pixels (a square
    window), or eroded by ``-dilate_px`` when it is negative."""
    import torch.nn.functional as F

    fg = (foreground.detach().float() > 0.5).float()
    if dilate_px > 0:
        fg = F.max_pool2d(fg[:, None], 2 * dilate_px + 1, stride=1, padding=dilate_px)[:, 0]
    elif dilate_px < 0:
        fg = -F.max_pool2d(-fg[:, None], 2 * -dilate_px + 1, stride=1, padding=-dilate_px)[:, 0]
    return fg > 0.5


def _in_every_matte(points: Tensor, cameras: Cameras, mattes: Tensor) -> Tensor:
    """``bool [N]``: whether each of ``points [N, 3]`` (world) projects onto ``mattes [V, H, W]``
    (``_mattes``) in every view of ``cameras [V]`` whose image it falls inside (in front of the
    camera); a view whose image a point leaves does not judge it."""
    return _matte_votes(points, cameras, mattes)[0]


def midline_reflection(head_to_world: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(A [3, 3], b [3])``: world points mirrored about the head's midline plane (head frame
    ``x = 0``, ``docs/conventions.md``) are ``p @ A.T + b``. ``head_to_world`` ``[4, 4]`` (rigid;
    ``None``: the world is the head frame)."""
    h2w = np.eye(4) if head_to_world is None else np.asarray(head_to_world, dtype=np.float64)
    r, t = h2w[:3, :3], h2w[:3, 3]
    a = r @ np.diag([-1.0, 1.0, 1.0]) @ r.T
    return a, t - a @ t


def _mirrored(points: Tensor, reflection: tuple[np.ndarray, np.ndarray]) -> Tensor:
    a, b = (torch.as_tensor(x, dtype=points.dtype, device=points.device) for x in reflection)
    return points @ a.T + b


def carve_into_mattes(points: Tensor, cameras: Cameras, foreground: Tensor, centre: Tensor | None = None,
                      step_m: float = 0.005, max_m: float = 0.05, dilate_px: int = 1,
                      mirror: tuple[np.ndarray, np.ndarray] | None = None, mirror_max_m: float = 0.02) -> Tensor:
    """``points [N, 3]`` (world, metres) each moved towards ``centre`` (default the origin: the
    tracker's head centre) in steps of ``step_m``, by at most ``max_m``, until it projects onto
    foreground (> 0.5, the matte dilated by ``dilate_px`` pixels for a pixel of misregistration)
    in every view whose image it falls inside; a view whose image a point leaves does not judge it.
    A point that no step brings inside stays where it was. With ``mirror`` (``midline_reflection``),
    a step counts only when the point's mirror image projects onto the mattes too, for at most
    ``mirror_max_m`` beyond the first step that holds the point alone (or where that step puts it,
    when ``max_m`` runs out first): the head is about left-right symmetric, so a side photo's outline
    bounds the back of the head on the side it does not see (issue 17: with one side photo left out,
    the shell stood 1-2 cm beyond the back of phone-5's head in that photo's view), but a wrong
    tracked pose or hair worn to one side can leave a mirror image outside every step; unbounded,
    those points stayed put while their neighbours moved in, as dark blobs in the air.

    Why (issue 17, the real photo sets' orbit renders): the back-of-head shell (``prior.back_shell``)
    lies on the fitted head, which can be wider or longer than the person's (short hair at the back,
    a skull fitted a few millimetres wide): from a frontal camera its opaque dark discs then stand
    out beside the hair as dark rims, and at a profile's own camera beyond the back of the head.
    Every photo's matte says the head is not there.

    ``cameras [V]`` of size ``W x H`` and ``foreground [V, H, W]`` in [0, 1]
    (``gaussian_head.foreground_weight`` of the matted inputs). Raises ``ValueError`` on mismatched
    shapes or a non-positive step.
    """
    import torch.nn.functional as F

    cams = cameras.flatten().to(points.device, torch.float32)
    v, h, w = len(cams.K), cams.height, cams.width
    if tuple(foreground.shape) != (v, h, w) or points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"carve_into_mattes: expected points [N, 3] and foreground [{v}, {h}, {w}], got {list(points.shape)}, {list(foreground.shape)}")
    if step_m <= 0 or max_m < 0:
        raise ValueError(f"carve_into_mattes: step_m must be > 0 and max_m >= 0, got {step_m}, {max_m}")
    fg = _mattes(foreground.to(points.device), dilate_px)  # eroded for dilate_px < 0: the point at least that many pixels inside the outline
    c = torch.zeros(3, device=points.device) if centre is None else torch.as_tensor(centre, dtype=torch.float32, device=points.device)
    pts = points.detach().float()
    inward = F.normalize(c - pts, dim=-1)
    out = pts.clone()
    todo = torch.ones(len(pts), dtype=torch.bool, device=pts.device)
    alone_at = torch.full((len(pts),), -1, dtype=torch.long, device=pts.device)  # the first step the point alone is held at
    extra = round(mirror_max_m / step_m)
    for k in range(round(max_m / step_m) + 1):
        if not bool(todo.any()):
            break
        idx = todo.nonzero()[:, 0]
        q = pts[idx] + inward[idx] * (k * step_m)
        ok = _in_every_matte(q, cams, fg)
        if mirror is not None:
            first = ok & (alone_at[idx] < 0)
            alone_at[idx[first]] = k
            ok &= _in_every_matte(_mirrored(q, mirror), cams, fg) | (k - alone_at[idx] >= extra)
        out[idx[ok]] = q[ok]
        todo[idx[ok]] = False
    late = todo & (alone_at >= 0)  # held alone but not with the mirror image within max_m: where the point alone is held
    out[late] = pts[late] + inward[late] * (alone_at[late, None].float() * step_m)
    return out.to(points.dtype)


HAIR_CARVE_STEPS = (1.0, 0.75, 0.5, 0.25, 0.0)  # hair_carve_fractions' fractions of the hair thickness, tried in this order


def hair_carve_fractions(surface: HeadSurface, cameras: Cameras, foreground: Tensor, hair_m: float, dilate_px: int = 1, max_up: float = 1.0,
                         mirror: bool = False) -> np.ndarray:
    """``[Nv]`` fraction (one of ``HAIR_CARVE_STEPS``) of the hair thickness ``hair_m`` each ICT-FaceKit
    vertex keeps: the largest whose laid-out point (``hair_vertex_weight`` x normal, on view 0's
    tracked head; the scalp does not move with expressions) projects onto foreground (> 0.5, the
    matte dilated by ``dilate_px`` pixels) in every view whose image it falls inside.

    Why (issue 17, the real photo sets' orbit renders): ``fit_hair_thickness`` chooses one thickness
    for the whole scalp from how the mattes are filled above the brows, mostly by the hair on top.
    Where the hair is thinner (at the temples, the back of a short-haired head) the laid-out scalp
    stands out beyond the photos' outlines, and a turned photo's hair pixels, laid on it, draw dark
    lobes beside the head in a frontal render ("headphones"). A point inside the head projects onto
    the person from every direction, so only the outline is carved. Vertices without hair get 1.

    ``cameras [V]`` of size ``W x H``, ``foreground [V, H, W]`` in [0, 1]. Raises ``ValueError`` on
    mismatched shapes.
    """

    from ..data.headmodel import HeadModel

    cams = cameras.flatten().to("cpu", torch.float32)
    v, h, w = len(cams.K), cams.height, cams.width
    if v != len(surface) or tuple(foreground.shape) != (v, h, w):
        raise ValueError(f"hair_carve_fractions: expected {len(surface)} cameras and foreground [{len(surface)}, {h}, {w}], got {v}, {list(foreground.shape)}")
    head = HeadModel.load()
    frac = np.ones(head.num_vertices, np.float32)
    if hair_m <= 0:
        return frac
    fg = _mattes(foreground.cpu(), dilate_px) | surface.padding(w, h)  # the crop's padding says nothing: it holds every point
    vw, off = _hair_offsets(surface, 0, head, head.visible_faces(eyelashes=False))
    undecided = np.linalg.norm(off, axis=1) > 0
    up = np.zeros(3)
    up[1] = 1.0
    if surface.head_to_world is not None:
        up = np.asarray(surface.head_to_world, dtype=np.float64)[:3, :3] @ up
    reflection = midline_reflection(surface.head_to_world) if mirror else None
    nrm = off / np.maximum(np.linalg.norm(off, axis=1, keepdims=True), 1e-12)
    undecided &= nrm @ up <= max_up  # the top of the head (normals within acos(max_up) of up) keeps its thickness
    for step in HAIR_CARVE_STEPS:
        if not undecided.any():
            break
        idx = np.nonzero(undecided)[0]
        pts = torch.from_numpy((vw[idx] + step * hair_m * off[idx]).astype(np.float32))
        ok = _in_every_matte(pts, cams, fg)
        if reflection is not None:  # its mirror image about the head's midline must project onto the mattes too
            ok &= _in_every_matte(_mirrored(pts, reflection), cams, fg)
        good = ok.numpy() | (step == HAIR_CARVE_STEPS[-1])
        frac[idx[good]] = step
        undecided[idx[good]] = False
    return frac


HULL_HALF_RANGE_M = 0.3  # hull_ray_depth: rays are marched over the head centre's distance +- this (metres)
HULL_STEP_M = 0.004  # ... in steps of this (metres)


def _matte_votes(points: Tensor, cameras: Cameras, mattes: Tensor, skip: Tensor | None = None, beyond: bool = False,
                 solid: Tensor | None = None, solid_t: Tensor | None = None, free_tol_m: float = 0.01) -> tuple[Tensor, Tensor]:
    """``(ok, judged)``, ``bool [N]`` each, for ``points [N, 3]`` (world): ``ok`` when the point
    projects onto ``mattes [V, H, W]`` in every view of ``cameras [V]`` whose image it falls inside
    (in front of the camera), ``judged`` when at least one view's image holds it. ``skip [N]``
    (long, optional): a view index per point that does not judge it (its own view). ``beyond``:
    a view also judges the points in front of it that project beyond its image, by the matte's
    nearest border pixel (the matte continued outwards: a torso cut by the bottom edge goes on,
    air beside a tight crop stays air). ``solid [V, H, W]`` (bool) and ``solid_t [V, H, W]`` (metres
    along the pixel's unit ray), optional: where a view sees a known surface (the tracked head), the
    space in front of it is empty: a point projecting onto such a pixel nearer its camera than
    ``solid_t - free_tol_m`` is not ``ok``."""
    v, h, w = mattes.shape
    ok = torch.ones(len(points), dtype=torch.bool, device=points.device)
    judged = torch.zeros_like(ok)
    for i in range(v):
        uv, z = cameras[i].project(points)
        x, y = uv[:, 0].floor().long(), uv[:, 1].floor().long()
        inside = (z > 0) if beyond else (x >= 0) & (x < w) & (y >= 0) & (y < h) & (z > 0)
        if skip is not None:
            inside &= skip != i
        yc, xc = y.clamp(0, h - 1), x.clamp(0, w - 1)
        good = mattes[i][yc, xc]
        if solid is not None:
            on = solid[i][yc, xc] & (x >= 0) & (x < w) & (y >= 0) & (y < h)
            dist = (points - cameras[i].centers).norm(dim=-1)
            good = good & ~(on & (dist < solid_t[i][yc, xc] - free_tol_m))
        ok &= ~inside | good
        judged |= inside
    return ok, judged


def hull_ray_depth(cameras: Cameras, foreground: Tensor, take: Tensor, centre: Tensor | None = None, prefer: Tensor | None = None,
                   half_m: float = HULL_HALF_RANGE_M, step_m: float = HULL_STEP_M, dilate_px: int = 2, beyond: bool = True,
                   solid: Tensor | None = None, solid_t: Tensor | None = None, free_tol_m: float = 0.01, middle: bool = False, chunk: int = 2048) -> Tensor:
    """Distance along each selected pixel's ray to the visual hull of the OTHER views' mattes.

    For every pixel of ``take`` the ray (``Cameras.pixel_rays``) is sampled from ``dc - half_m`` to
    ``dc + half_m`` in steps of ``step_m``, ``dc`` the distance along the ray to its point nearest
    ``centre`` (default the origin: the tracker's head centre). A sample is in the hull when it
    projects onto foreground (> 0.5, dilated by ``dilate_px`` pixels for misregistration) in every
    other view whose image it falls inside (in front of the camera), and at least one other view's
    image holds it: a view that does not see the point does not judge it, the pixel's own view never
    does (its ray lies on its own matte).

    Beyond an image's border a view judges by its matte's nearest border pixel (``beyond``, the
    default: a torso cut by the bottom edge goes on, the air beside a tight crop stays air; without
    it a point that leaves the crops of the views that would carve it stays in the hull: on phone-5's
    tight crops the entry lay 14 cm nearer the camera than the nearest head pixel's distance on
    average, 4 cm with it). With ``solid`` and
    ``solid_t`` the space between a view's camera and the surface it is known to see there (the
    tracked head's hit pixels and their distances, ``SurfaceDepth``) is empty too, up to
    ``free_tol_m``.

    Without ``prefer`` the pixel gets the first sample in the hull (where its ray enters it); with
    ``prefer [V, H, W]`` (metres, e.g. ``SurfaceDepth.t``) it keeps ``prefer`` when that point is
    in the hull and otherwise takes the hull sample nearest it; with ``middle``, halfway between its
    first and its last sample in the hull.

    Why (issue 17, the real photo sets): pixels that miss the tracked head (long hair beside the
    face, neck, shoulders) took the nearest head pixel's distance, which the other photos' mattes
    contradict; the visual hull of the photos is where such a point can be (``docs/model-card-log.md``
    "Off-head pixels on the photos' visual hull").

    Args:
        cameras: ``Cameras [V]`` of the ``W x H`` views.
        foreground: ``[V, H, W]`` in [0, 1] (``gaussian_head.foreground_weight`` of the matted inputs).
        take: ``[V, H, W]`` bool, the pixels to place.
        centre: ``[3]`` world point (metres) the interval is centred on.
        prefer: optional ``[V, H, W]`` distances (metres).
        half_m, step_m: the interval's half length and the step (metres, > 0).
        dilate_px: the mattes dilated by this many pixels (``_mattes``).
        beyond: judge points beyond a view's image by its border (above).
        solid, solid_t, free_tol_m: optional ``[V, H, W]`` bool and metres, and a tolerance (metres):
            the empty space in front of known surfaces (above).
        middle: the hull's middle along the ray instead of its entry (ignores ``prefer``).
        chunk: pixels marched at once (memory ``chunk x 2 half_m / step_m`` samples).
    Returns:
        ``[V, H, W]`` float32 distances (metres) along each unit ray; NaN where a pixel is not taken,
        or no sample of its ray is in the hull (no other view judges any, or every one is carved away).
    Raises:
        ValueError: on mismatched shapes or a non-positive step or interval.
    """
    cams = cameras.flatten().to(foreground.device, torch.float32)
    v, h, w = len(cams.K), cams.height, cams.width
    if tuple(foreground.shape) != (v, h, w) or tuple(take.shape) != (v, h, w) or (prefer is not None and tuple(prefer.shape) != (v, h, w)):
        raise ValueError(f"hull_ray_depth: foreground, take (and prefer) must have shape [{v}, {h}, {w}], got {list(foreground.shape)}, {list(take.shape)}"
                         + ("" if prefer is None else f", {list(prefer.shape)}"))
    if step_m <= 0 or half_m <= 0:
        raise ValueError(f"hull_ray_depth: step_m and half_m must be > 0, got {step_m}, {half_m}")
    dev = foreground.device
    out = torch.full((v, h, w), float("nan"), dtype=torch.float32, device=dev)
    idx = take.to(dev).reshape(-1).nonzero()[:, 0]
    if len(idx) == 0:
        return out
    mattes = _mattes(foreground, dilate_px)
    o, d = cams.pixel_rays()
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    c = torch.zeros(3, device=dev) if centre is None else torch.as_tensor(centre, dtype=torch.float32, device=dev)
    k = torch.arange(round(2 * half_m / step_m) + 1, device=dev, dtype=torch.float32) * step_m - half_m  # [K]
    pref = None if prefer is None else prefer.to(dev, torch.float32).reshape(-1)
    flat = out.reshape(-1)
    for a in range(0, len(idx), chunk):
        sel = idx[a : a + chunk]
        oo, dd = o[sel], d[sel]
        dc = ((c - oo) * dd).sum(-1)  # [P]
        s = dc[:, None] + k[None]  # [P, K]
        if pref is not None:
            s = torch.cat([pref[sel][:, None], s], 1)  # the preferred distance first: kept when in the hull
        p, n = s.shape
        pts = (oo[:, None] + s[..., None] * dd[:, None]).reshape(-1, 3)
        ok, judged = _matte_votes(pts, cams, mattes, (sel // (h * w)).repeat_interleave(n), beyond, solid, solid_t, free_tol_m)
        good = (ok & judged).reshape(p, n) & (s > 1e-3) & torch.isfinite(s)
        found = good.any(1)
        if middle:  # halfway between the first and the last sample in the hull
            first = good.float().argmax(1)
            last = n - 1 - good.flip(1).float().argmax(1)
            t = 0.5 * (s.gather(1, first[:, None])[:, 0] + s.gather(1, last[:, None])[:, 0])
            flat[sel[found]] = t[found]
            continue
        if pref is None:
            j = good.float().argmax(1)  # the first sample in the hull
        else:
            j = torch.where(good, (s - s[:, :1]).abs(), torch.full_like(s, float("inf"))).argmin(1)
        t = s.gather(1, j[:, None])[:, 0]
        flat[sel[found]] = t[found]
    return out


def off_head_on_hull(sd: SurfaceDepth, surface: HeadSurface, cameras: Cameras, foreground: Tensor, mode: str = "entry", collar: bool = False,
                     dilate_px: int = 2, beyond: bool = True, free_tol_m: float | None = None) -> SurfaceDepth:
    """``sd`` with its off-head pixels moved onto the visual hull of the other views' mattes
    (``hull_ray_depth``).

    The pixels moved: those of each view's own matte (``foreground > 0.5``) whose ray misses the
    head (``~sd.hit``, not ``beyond_face``), which ``surface_ray_depth`` gave the nearest head
    pixel's distance; with ``collar``, also the head pixels below the tracked neck ring
    (``neck_ring_vertices``: ICT's lower neck and collar) whose point is outside that hull. ``mode``:
    ``"entry"``, where the pixel's ray enters the hull; ``"nearest"``, the present distance where its
    point is in the hull, else the hull sample nearest it; ``"middle"``, halfway through the hull
    (the collar's pixels then take, as with ``"nearest"``, the hull sample nearest the mesh's point). A pixel whose ray no other view judges, or that
    no sample of its ray puts in the hull, keeps its distance.

    Measured on the real photo sets (``docs/model-card-log.md`` "Off-head pixels on the photos' visual
    hull"): no mode raised the leave-one-out means of all three sets; ``GaussianHeadConfig.off_head_hull``
    is off by default.

    Args:
        sd: ``surface_ray_depth`` of ``surface`` at ``cameras [V]`` (``W x H``).
        foreground: ``[V, H, W]`` in [0, 1] (``gaussian_head.foreground_weight``).
        mode, collar: above.
        dilate_px, beyond: ``hull_ray_depth``'s.
        free_tol_m: None, or the other views' head pixels also carve the space in front of them, up
            to this many metres (``hull_ray_depth``'s ``solid``).
    Returns:
        A new ``SurfaceDepth`` (``t`` changed; ``hit``, ``beyond_face``, ``face_hit`` as they were).
    Raises:
        ValueError: on an unknown mode or mismatched shapes.
    """
    if mode not in ("entry", "nearest", "middle"):
        raise ValueError(f"off_head_on_hull: mode must be 'entry', 'nearest' or 'middle', got {mode!r}")
    cams = cameras.flatten().to("cpu", torch.float32)
    v, h, w = len(cams.K), cams.height, cams.width
    if tuple(sd.t.shape) != (v, h, w) or tuple(foreground.shape) != (v, h, w) or len(surface) != v:
        raise ValueError(f"off_head_on_hull: expected {len(surface)} views, sd.t and foreground [{v}, {h}, {w}], got {list(sd.t.shape)}, {list(foreground.shape)}")
    fg = foreground.detach().float().cpu()
    t0 = sd.t.float().cpu()
    centre = surface.centre
    take = sd.off_head(fg)
    t = t0.clone()
    free = {} if free_tol_m is None else {"solid": sd.hit.cpu(), "solid_t": t0, "free_tol_m": free_tol_m}
    th = hull_ray_depth(cams, fg, take, centre, prefer=t0 if mode == "nearest" else None, dilate_px=dilate_px, beyond=beyond, middle=mode == "middle", **free)
    ok = torch.isfinite(th)
    t[ok] = th[ok]
    if collar:
        from ..data.headmodel import HeadModel

        head = HeadModel.load()
        ring = neck_ring_vertices(head)
        up = torch.tensor([0.0, 1.0, 0.0]) if surface.head_to_world is None else torch.as_tensor(np.asarray(surface.head_to_world)[:3, 1], dtype=torch.float32)
        o, d = cams.pixel_rays()
        low = torch.zeros(v, h, w, dtype=torch.bool)
        for i in range(v):
            ring_low = float((torch.from_numpy(surface.vertices(i, head)[ring]).float() @ up).min())
            low[i] = ((o[i] + t0[i][..., None] * d[i]) @ up) < ring_low
        cand = sd.hit.cpu() & low & (fg > 0.5)
        tn = hull_ray_depth(cams, fg, cand, centre, prefer=t0, dilate_px=dilate_px, beyond=beyond, **free)
        moved = torch.isfinite(tn) & (tn != t0)  # the mesh's point is outside the hull
        if mode == "entry":
            tn = hull_ray_depth(cams, fg, moved, centre, dilate_px=dilate_px, beyond=beyond, **free)
        ok = moved & torch.isfinite(tn)
        t[ok] = tn[ok]
    return SurfaceDepth(t.to(sd.t), sd.hit, sd.beyond_face, sd.face_hit)


OFF_HEAD_DRAW_MODES = ("off", "behind", "drop", "sharp", "headon_sharp", "cover_sharp", "under")


def off_head_draw_flags(sd: SurfaceDepth, cameras: Cameras, foreground: Tensor, mode: str, views: int | None = None,
                        behind_m: float = 0.02, tol_m: float = 0.01) -> tuple[SurfaceDepth, Tensor | None]:
    """Where and when the off-head pixels' Gaussians are drawn (``GaussianHeadConfig.off_head_draw``).

    The off-head pixels are those of each view's matte (``foreground > 0.5``) whose ray misses the
    head (``~sd.hit``, not ``beyond_face``): ``surface_ray_depth`` lays them at the nearest head
    pixel's distance, and seen from another input camera some of them lie across that view's face
    (``docs/model-card-log.md`` "Off-head pixels on the photos' visual hull"). ``mode``:

    - ``"off"``: unchanged (``sd``, None).
    - ``"behind"``: their distance along their own ray grows by ``behind_m`` metres: their own view
      sees them where it did, other views see them further back, behind the face's outline.
    - ``"drop"``: those in front of another real view's head (``coverage.in_front_of_other_heads``,
      judged by the first ``views`` views, tolerance ``tol_m``) are marked ``beyond_face``, so
      ``reconstruct`` drops their Gaussians.
    - ``"sharp"``: all of them are returned as the sharp map (drawn near their own camera only,
      ``viewblend.ViewBlend.sharp``).
    - ``"headon_sharp"``: as ``"sharp"``; ``reconstruct`` keeps only those a covering real view sees
      at least ``gaussians.head_on_gain_deg`` more head-on (``viewblend.contradicted_by_head_on_view``
      with any colour counting as a contradiction).
    - ``"cover_sharp"``: those in front of another real view's head are the sharp map.
    - ``"under"``: all of them are returned as the map; ``reconstruct`` records it as
      ``ViewBlend.under``: in every frame they are drawn under the other Gaussians (where the head
      leaves the frame uncovered), ``viewblend.push_under``.

    Args:
        sd: ``surface_ray_depth`` of ``V`` views at ``cameras [V]`` (``W x H``), mirrored views included.
        foreground: ``[V, H, W]`` in [0, 1].
    Returns:
        ``(sd', sharp)``: the (possibly changed) ``SurfaceDepth`` and a ``bool [V, H, W]`` map of the
        pixels whose Gaussians are to be drawn sharply, or None.
    Raises:
        ValueError: on an unknown mode.
    """
    if mode not in OFF_HEAD_DRAW_MODES:
        raise ValueError(f"off_head_draw_flags: mode must be one of {OFF_HEAD_DRAW_MODES}, got {mode!r}")
    if mode == "off":
        return sd, None
    off = sd.off_head(foreground)
    if mode == "behind":
        t = sd.t.clone()
        t[off.to(t.device)] += float(behind_m)
        return SurfaceDepth(t, sd.hit, sd.beyond_face, sd.face_hit), None
    if mode in ("sharp", "headon_sharp", "under"):
        return sd, off
    from .coverage import in_front_of_other_heads

    bad = in_front_of_other_heads(sd.t, sd.hit, off, cameras, foreground, views, tol_m)
    if mode == "drop":
        return SurfaceDepth(sd.t, sd.hit, sd.beyond_face | bad.to(sd.beyond_face.device), sd.face_hit), None
    return sd, bad


def below_chin(points: Tensor, surface: HeadSurface, margin_m: float = 0.0) -> Tensor:
    """``bool [N]``: which of ``points [N, 3]`` (world, metres) lie lower than the tracked head's chin
    by more than ``margin_m`` metres, measured along the head's up axis.

    The chin is ICT-FaceKit's landmark 8 (``HeadModel.landmarks68``, the Multi-PIE chin point) of
    ``surface``'s identity at the neutral expression; the up axis is the head frame's +y
    (``docs/conventions.md``), both moved into the world by ``surface.head_to_world`` when set.
    ``margin_m`` may be negative (then points up to that far above the chin count too).

    Why (issue 17, the real photo sets' leave-one-out renders, ``docs/model-card-log.md`` "Mirrored
    views below the chin"): a mirrored view (``model/mirror.py``) is the mirror image of a turned
    photo, a guess at the unseen side of a head that is left-right symmetric; below the chin the
    photo shows the neck, the collar and the shoulders, which are not: the torso is turned less than
    the head, or not at all, so the mirrored neck and T-shirt land on the wrong side and draw skin
    over the shoulders. ``FastGHA.reconstruct`` draws those Gaussians under the others
    (``GaussianHeadConfig.mirror_under_below_chin``).
    Raises ``ValueError`` when ``points`` is not ``[N, 3]``.
    """
    from ..data.headmodel import HeadModel

    if points.ndim != 2 or points.shape[-1] != 3:
        raise ValueError(f"below_chin: points must be [N, 3], got {list(points.shape)}")
    head = HeadModel.load()
    ident = np.zeros(head.num_identity, np.float32)
    n = min(head.num_identity, len(surface.identity))
    ident[:n] = surface.identity[:n]
    chin = np.asarray(head.vertices(ident, None), dtype=np.float64)[int(head.landmarks68[8])]
    up = np.array([0.0, 1.0, 0.0])
    if surface.head_to_world is not None:
        h = np.asarray(surface.head_to_world, dtype=np.float64)
        chin, up = h[:3, :3] @ chin + h[:3, 3], h[:3, :3] @ up
    c = torch.as_tensor(chin, dtype=torch.float32, device=points.device)
    u = torch.as_tensor(up, dtype=torch.float32, device=points.device)
    return ((points.detach().float() - c) @ u) < -float(margin_m)


def off_head_behind_ears(sd: SurfaceDepth, surface: HeadSurface, cameras: Cameras, lateral_m: float = BESIDE_FACE_LATERAL_M,
                         max_angle_deg: float = BESIDE_FACE_MAX_ANGLE_DEG, max_move_m: float = BESIDE_FACE_MAX_MOVE_M) -> SurfaceDepth:
    """``sd`` with the off-head pixels beside the face pushed back along their rays, no nearer the
    camera than the plane of the ears.

    Which pixels: those whose ray misses the head (``~sd.hit``) and whose nearest-hit placement
    lies, in the head frame of their view's tracked head, more than ``lateral_m`` metres to the side
    of the midline (``|x| > lateral_m``: beyond the jaw, whose corners are 7.4 cm out on the ICT mean
    head), above the chin (ICT's landmark 8) and below the brows (the mean height of landmarks 17-26),
    both at the view's expression, and in front of the ears' coronal plane (``z > 0``: the head frame's origin lies between the ears, ``docs/conventions.md``),
    in a view that looks at the face within ``max_angle_deg`` of the head's front-back axis (the ray's
    head-frame direction has ``-z >= cos(max_angle_deg)``). Each moves along its own ray to where the
    ray crosses that plane (``z = 0``): only further from its camera, and only when that is at most
    ``max_move_m`` away; its own camera still sees it where it was, and the rest of ``sd`` is unchanged.
    Above the brows nothing moves: hair above the temples of phone-5's frontal and pitched photos,
    moved back, drew spikes above its head in other views. The hair beside the cheeks needs 6-15 cm
    (a 6 cm limit, shipped before the brow limit, left the blot below in place; measured,
    ``docs/model-card-log.md``).

    Why (issue 17, studio-4's leave-one-out render at -70 degrees, ``docs/model-card-log.md`` "Hair beside
    the face"): a frontal photo's long hair hanging beside the cheeks misses the bald head model, so
    ``surface_ray_depth`` gives it the distance of the nearest head pixel, the cheek's outline: 3-5 cm
    in front of where hair falls from the scalp. Seen from the side, those Gaussians stand in the air
    in front of the mouth, and since off-head Gaussians are drawn under the others
    (``off_head_draw = "under"``), exactly there, where no other Gaussian covers them, they show as a
    dark blot before the lips. Pixels near the midline (a profile's nose and lips beyond the mesh,
    hair above the crown), above the brows (the temples) and below the chin (neck, collar, chest)
    keep their placement.

    Args:
        sd: ``SurfaceDepth`` of ``V`` views (``surface_ray_depth``).
        surface: the ``V`` views' tracked head (``HeadSurface``).
        cameras: ``Cameras [V]`` of the views (world = ``surface``'s world).
        lateral_m: the half-width (metres) beyond which an off-head pixel counts as beside the face.
        max_angle_deg: the views whose rays lie within this angle (degrees, in (0, 90]) of the head's
            backward axis are the ones whose pixels move.
        max_move_m: the largest move (metres) along a ray; pixels that would move further stay.
    Returns:
        a new ``SurfaceDepth`` (``t`` changed where moved; ``hit``, ``beyond_face``, ``face_hit`` shared).
    Raises:
        ValueError: when the views' counts or sizes differ, ``lateral_m`` or ``max_move_m`` is not
            positive, or ``max_angle_deg`` is outside (0, 90].
    """
    from ..data.headmodel import HeadModel

    cams = cameras.flatten()
    v, h, w = sd.t.shape
    if len(cams.K) != v or len(surface) != v or (cams.width, cams.height) != (w, h):
        raise ValueError(f"off_head_behind_ears: {v} depth maps of {w}x{h}, {len(surface)} surface views and {len(cams.K)} cameras of {cams.width}x{cams.height}")
    if not (lateral_m > 0 and max_move_m > 0):
        raise ValueError(f"off_head_behind_ears: lateral_m and max_move_m must be > 0, got {lateral_m} and {max_move_m}")
    if not 0 < max_angle_deg <= 90:
        raise ValueError(f"off_head_behind_ears: max_angle_deg must be in (0, 90], got {max_angle_deg}")
    head = HeadModel.load()
    chin_y = surface.points([int(head.landmarks68[8])], head)  # [V, 1, 3] world
    brows = surface.points([int(j) for j in head.landmarks68[17:27]], head)  # [V, 10, 3] world
    h2w = np.eye(4) if surface.head_to_world is None else np.asarray(surface.head_to_world, dtype=np.float64)
    w2h = np.linalg.inv(h2w)
    origins, dirs = cams.to(dtype=torch.float64).pixel_rays()  # [V, H, W, 3] world, unit directions
    t = sd.t.clone()
    for i in range(v):
        o = origins[i].numpy() @ w2h[:3, :3].T + w2h[:3, 3]
        d = dirs[i].numpy() @ w2h[:3, :3].T
        p = o + sd.t[i].double().numpy()[..., None] * d
        chin = (chin_y[i, 0].astype(np.float64) @ w2h[:3, :3].T + w2h[:3, 3])[1]
        brow = float((brows[i].astype(np.float64) @ w2h[:3, :3].T + w2h[:3, 3])[:, 1].mean())
        with np.errstate(divide="ignore", invalid="ignore"):
            t_plane = np.where(d[..., 2] < 0, -o[..., 2] / d[..., 2], -np.inf)
        t0 = sd.t[i].double().numpy()
        move = (~sd.hit[i].numpy() & (np.abs(p[..., 0]) > lateral_m) & (p[..., 1] > chin) & (p[..., 1] < brow) & (p[..., 2] > 0)
                & (-d[..., 2] >= np.cos(np.radians(max_angle_deg))) & (t_plane > t0) & (t_plane - t0 <= max_move_m))
        t[i][torch.from_numpy(move)] = torch.from_numpy(t_plane[move].astype(np.float32))
    return SurfaceDepth(t, sd.hit, sd.beyond_face, sd.face_hit)


OFF_HEAD_SMOOTH_AXES = ("vertical", "both")  # smooth_off_head_depth's neighbours: the pixels above and below, or also left and right


def smooth_off_head_depth(sd: SurfaceDepth, foreground: Tensor, length: float, fixed: Tensor | None = None, axis: str = "vertical",
                          hold: float = 0.0) -> SurfaceDepth:
    """``sd`` with the off-head pixels' ray distances relaxed towards a membrane between the head's.

    ``surface_ray_depth`` gives every pixel whose ray misses the head the distance of its nearest hit
    pixel: a piecewise-constant field, constant along the lines to each boundary point, whose
    neighbouring pixels jump by centimetres where their nearest hit points differ (on studio-4's
    frontal photo, 57 neighbour steps above 3 cm in its long hair). Seen from another camera, the two
    sides of such a step move apart and a slit of background opens through the hair (the white
    streaks across the hair tips of studio-4's pitched-up leave-one-out render; ``docs/model-card-log.md``
    "Slits through long hair"). Here the off-head pixels inside their view's matte (``~sd.hit``,
    ``foreground > 0.5``, not ``fixed``) take, by Jacobi iterations from the nearest-hit values, the
    mean of their neighbours inside the matte or on the head: the hit (and ``fixed``) pixels hold their
    distances, the matte's outline lets nothing in. ``length`` sets how far the relaxation reaches:
    ``round((length * S)^2)`` iterations for ``S``-pixel views, a diffusion length of about
    ``length * S`` pixels, so the result does not depend on the input size. The off-head pixels
    within ``round(hold * S)`` pixels of the head's outline keep their distance too: there the
    nearest head pixel is the best guess (hair lies against the head), and that hair frames the face
    in frontal views (relaxed, studio-4's +55 degree render lost the hair behind its ear, 15.63 ->
    14.90 dB, and dlib read its avatar's open jaw 0.03 shorter, on frames whose mouths were the same).

    Args:
        sd: ``SurfaceDepth`` of ``V`` views of ``S x S`` pixels (``surface_ray_depth``).
        foreground: ``[V, S, S]`` matte weights (``gaussian_head.foreground_weight``).
        length: the diffusion length as a fraction of the views' side (0 = ``sd`` unchanged).
        hold: the band beside the head's outline that keeps its distances, as a fraction of the
            views' side (0 = none).
        fixed: ``bool [V, S, S]`` more pixels that keep their distance (e.g. those
            ``off_head_behind_ears`` placed), or None.
        axis: ``"vertical"``: each pixel averages the pixels above and below it only, along the way
            long hair hangs: a torso beside a turned head, whose nearest-hit distances change from
            the throat to the nape across the image, is not tilted into a sheet (relaxed both ways,
            phone-5's -70 degree photo's shoulder drew pale stripes over the neck of its pitched-up
            render); ``"both"``: the four neighbours.
    Returns:
        a new ``SurfaceDepth`` (``t`` changed on the relaxed pixels; ``hit``, ``beyond_face``, ``face_hit`` shared).
    Raises:
        ValueError: on a negative ``length``, an unknown ``axis`` or shapes that do not match ``sd.t``.
    """
    if not (length >= 0 and hold >= 0):
        raise ValueError(f"smooth_off_head_depth: length and hold must be >= 0, got {length} and {hold}")
    if axis not in OFF_HEAD_SMOOTH_AXES:
        raise ValueError(f"smooth_off_head_depth: axis must be one of {OFF_HEAD_SMOOTH_AXES}, got {axis!r}")
    v, h, w = sd.t.shape
    if tuple(foreground.shape) != (v, h, w) or (fixed is not None and tuple(fixed.shape) != (v, h, w)):
        raise ValueError(f"smooth_off_head_depth: foreground and fixed must be [{v}, {h}, {w}] like sd.t, got "
                         f"{list(foreground.shape)} and {None if fixed is None else list(fixed.shape)}")
    iters = int(round((length * max(h, w)) ** 2))
    if iters == 0:
        return sd
    fg = foreground.detach().float().cpu() > 0.5
    held = sd.hit.cpu() if fixed is None else sd.hit.cpu() | fixed.cpu()
    band = int(round(hold * max(h, w)))
    if band > 0:  # beside the head's outline: the nearest head pixel's distance stays
        held = held | (torch.nn.functional.max_pool2d(sd.hit.cpu()[:, None].float(), 2 * band + 1, 1, band)[:, 0] > 0)
    free = (~held & fg)[:, None]
    valid = (sd.hit.cpu() | fg)[:, None].float()
    kernel = torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0]]) if axis == "vertical" else torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    kernel = kernel.view(1, 1, 3, 3)
    count = torch.nn.functional.conv2d(valid, kernel, padding=1)  # valid neighbours, constant over the iterations
    inv = torch.where(count > 0, 1.0 / count.clamp_min(1.0), torch.zeros_like(count))
    free = free & (count > 0)
    x = sd.t.cpu().float()[:, None].clone()
    for _ in range(iters):
        avg = torch.nn.functional.conv2d(x * valid, kernel, padding=1) * inv
        x = torch.where(free, avg, x)
    return SurfaceDepth(x[:, 0].to(sd.t.device, sd.t.dtype), sd.hit, sd.beyond_face, sd.face_hit)


EXTRUDE_STEP_M = 0.006  # off_head_extrusion: the copies' spacing along their ray (metres)
EXTRUDE_NEAR_M = 0.05  # ... copies no farther than this from the view's fitted head (metres)
EXTRUDE_RAY_SLACK_M = 0.2  # ... copies are tried up to depth_m + this far along the ray (metres; an oblique ray from in front of the ears needs more than depth_m)
EXTRUDE_HAIR_TOL = 0.3  # ... source pixels within this RGB distance (0..1 channels) of the view's hair colour, and nearer it than the skin's


def off_head_extrusion(sd: SurfaceDepth, surface: HeadSurface, cameras: Cameras, foreground: Tensor, images: Tensor, views: int,
                       depth_m: float = 0.10, step_m: float = EXTRUDE_STEP_M, near_m: float = EXTRUDE_NEAR_M,
                       hair_tol: float = EXTRUDE_HAIR_TOL, lateral_m: float = BESIDE_FACE_LATERAL_M,
                       max_angle_deg: float = BESIDE_FACE_MAX_ANGLE_DEG, dilate_px: int = 2, mirror: bool = True) -> tuple[Tensor, Tensor]:
    """Copies of the hair pixels beside the head further back along their rays: the depth of long hair
    that a frontal photo sees only as a strip beside the face.

    Why (issue 17, studio-4's leave-one-out render at +55 degrees): a frontal photo's long hair
    hanging beside the cheeks lies on one surface (``off_head_behind_ears``: the ears' plane), so a
    view from the side finds nothing behind the ear where the hair hangs down to the shoulder: 6.3 %
    of that photo's matte was left uncovered (``docs/model-card-log.md`` "Long hair behind the ears").

    Which pixels: the off-head pixels (``SurfaceDepth.off_head``) of the first ``views`` views (the
    real photos) that look at the face within ``max_angle_deg`` of the head's front-back axis, whose
    point lies more than ``lateral_m`` to the side of the midline and below the mean height of the
    brows (head frame of the tracked head, ``docs/conventions.md``), and whose colour is the hair's:
    within ``hair_tol`` (RGB distance, channels in [0, 1]) of the median colour of the view's head
    pixels above the brows (2 cm up, off the bare face) and nearer it than the median colour of the
    bare face's pixels (``SurfaceDepth.face_hit``): ears, neck and skin stay single (extruded, a
    short-haired head's ears stood as fins behind it). A view without 10 pixels of either keeps its
    pixels single.

    Each such pixel gets copies at ``t + k step_m`` (k = 1, 2, ...) along its unit ray while the copy
    lies no more than ``depth_m`` behind the ears' coronal plane (head frame ``z >= -depth_m``), within
    ``near_m`` of the view's fitted head vertices, and projects onto the matte (dilated by
    ``dilate_px``) of every other real view that sees it, not in front of the head surface that view
    sees there (``_matte_votes`` with ``beyond`` and the views' head pixels as ``solid``); with
    ``mirror``, its mirror image about the head's midline (``midline_reflection``) must pass the same
    test in every real view (the side of the head that no remaining photo sees, as
    ``hair_carve_fractions(mirror=True)``: a short-haired head's other side photo rules the copies
    out). A pixel's copies stop at its first copy that fails.

    Args:
        sd: ``surface_ray_depth`` (after ``off_head_behind_ears``) of ``V`` views, ``W x H``
            (mirrored virtual views after the real ones).
        surface: the real views' tracked head (``HeadSurface``, at least ``views`` views).
        cameras: ``Cameras [V]`` (world = ``surface``'s world).
        foreground: ``[V, H, W]`` in [0, 1] (``gaussian_head.foreground_weight``).
        images: ``[V, 3, H, W]`` the matted inputs, RGB in [0, 1].
        views: how many leading views are real photos (mirrored virtual views after them neither
            give copies nor judge).
        depth_m, step_m, near_m: metres, > 0.
    Returns:
        ``(source, points)``: ``long [M]`` each copy's pixel as the flat index ``i * H * W + y * W + x``
        and ``float32 [M, 3]`` its world position (metres).
    Raises:
        ValueError: on mismatched shapes, ``views`` outside ``[1, V]`` or a non-positive length.
    """
    from scipy.spatial import cKDTree

    from ..data.headmodel import HeadModel

    cams = cameras.flatten().to("cpu", torch.float32)
    v, h, w = sd.t.shape
    if len(cams.K) != v or (cams.width, cams.height) != (w, h):
        raise ValueError(f"off_head_extrusion: {v} depth maps of {w}x{h} and {len(cams.K)} cameras of {cams.width}x{cams.height}")
    if tuple(foreground.shape) != (v, h, w) or tuple(images.shape) != (v, 3, h, w):
        raise ValueError(f"off_head_extrusion: foreground must be [{v}, {h}, {w}] and images [{v}, 3, {h}, {w}], got {list(foreground.shape)} and {list(images.shape)}")
    if not 1 <= views <= v:
        raise ValueError(f"off_head_extrusion: views must be in [1, {v}], got {views}")
    if len(surface) < views:
        raise ValueError(f"off_head_extrusion: the surface holds {len(surface)} views, fewer than the {views} real ones")
    if not (depth_m > 0 and step_m > 0 and near_m > 0):
        raise ValueError(f"off_head_extrusion: depth_m, step_m and near_m must be > 0, got {depth_m}, {step_m}, {near_m}")
    head = HeadModel.load()
    brows = surface.points([int(j) for j in head.landmarks68[17:27]], head)  # [V, 10, 3] world
    h2w = np.eye(4) if surface.head_to_world is None else np.asarray(surface.head_to_world, dtype=np.float64)
    h2w_t, w2h = torch.from_numpy(h2w).float(), torch.from_numpy(np.linalg.inv(h2w)).float()
    origins, dirs = cams.pixel_rays()  # [V, H, W, 3] world, unit directions
    fg = foreground.detach().float().cpu() > 0.5
    off = sd.off_head(foreground)
    mattes = _mattes(foreground[:views].detach().float().cpu(), dilate_px)
    solid, solid_t = sd.hit[:views].cpu() & fg[:views], sd.t[:views].float().cpu()
    refl = midline_reflection(surface.head_to_world) if mirror else None
    k = torch.arange(1, int(np.floor((depth_m + EXTRUDE_RAY_SLACK_M) / step_m)) + 1, dtype=torch.float32) * step_m  # [K] candidate steps along the ray
    sources, points = [], []
    for i in range(views):
        o = origins[i] @ w2h[:3, :3].T + w2h[:3, 3]  # head frame
        d = dirs[i] @ w2h[:3, :3].T
        t0 = sd.t[i].float().cpu()
        p = o + t0[..., None] * d  # [H, W, 3]
        brow = float((torch.from_numpy(brows[i]).float() @ w2h[:3, :3].T + w2h[:3, 3])[:, 1].mean())
        im = images[i].detach().float().cpu()
        face = (sd.face_hit[i].cpu() if sd.face_hit is not None else sd.hit[i].cpu()) & fg[i]
        scalp = sd.hit[i].cpu() & fg[i] & ~face & (p[..., 1] > brow + 0.02)
        if int(face.sum()) < 10 or int(scalp.sum()) < 10:
            continue
        skin, hair = im[:, face].median(dim=1).values, im[:, scalp].median(dim=1).values  # [3] each
        d_skin, d_hair = (im - skin[:, None, None]).norm(dim=0), (im - hair[:, None, None]).norm(dim=0)
        take = (off[i] & (p[..., 0].abs() > lateral_m) & (p[..., 1] < brow) & (-d[..., 2] >= np.cos(np.radians(max_angle_deg)))
                & (d_hair < d_skin) & (d_hair < hair_tol))
        idx = take.reshape(-1).nonzero()[:, 0]
        if len(idx) == 0:
            continue
        tt = t0.reshape(-1)[idx][:, None] + k[None]  # [P, K]
        ph = o.reshape(-1, 3)[idx][:, None] + tt[..., None] * d.reshape(-1, 3)[idx][:, None]  # [P, K, 3] head frame
        pw = ph.reshape(-1, 3) @ h2w_t[:3, :3].T + h2w_t[:3, 3]
        ok = ph[..., 2].reshape(-1) >= -depth_m
        others = [r for r in range(views) if r != i]
        if others:
            ok &= _matte_votes(pw, cams[others], mattes[others], None, True, solid[others], solid_t[others])[0]
        if refl is not None:
            ok &= _matte_votes(_mirrored(pw, refl), cams[:views], mattes, None, True, solid, solid_t)[0]
        dist, _ = cKDTree(surface.vertices(i, head)).query(pw.numpy(), distance_upper_bound=near_m)
        ok &= torch.from_numpy(np.isfinite(dist))
        ok = ok.reshape(len(idx), len(k)).int().cumprod(1).bool()  # each pixel's copies stop at the first that fails
        pi, ki = ok.nonzero(as_tuple=True)
        sources.append(i * h * w + idx[pi])
        points.append(pw.reshape(len(idx), len(k), 3)[pi, ki])
    if not sources:
        return torch.zeros(0, dtype=torch.long), torch.zeros(0, 3)
    return torch.cat(sources), torch.cat(points)
