"""Photos -> request data: detect, fit, camera, crop, matte (the `fastgha track` pipeline)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import torch

from ..cameras import Cameras
from .camera import pose_to_cameras
from .crop import DEFAULT_EXTENT_M, background_uint8, crop_array, crop_cameras, head_crop_box
from .fit import FitConfig, FitResult, LandmarkModel, default_intrinsics, fit_known_cameras, fit_landmarks, intrinsics_from_35mm, landmark_models
from .matting import MattingConfig, head_silhouette, matte_from_head
from .photoalign import PhotoAlignConfig, PhotoAlignResult, register_photos
from .silhouette import SilhouetteTarget, person_mask

__all__ = ["PHOTO_ALIGN_MODES", "TURNED_MIN_YAW_DEG", "TrackConfig", "TrackedPhotos", "track_photos", "tracked_photos_from_fit", "track_request", "track_known_cameras", "known_camera_fit_config"]

logger = logging.getLogger(__name__)


PHOTO_ALIGN_MODES = ("off", "turned", "all")  # TrackConfig.with_photo_align
# |yaw| (degrees) from which the landmark fit saturates on synthetic renders (FitConfig.yaw_prior_min_deg's
# 55): the photos the default registration corrects; the others hold their landmark poses
TURNED_MIN_YAW_DEG = 55.0


@dataclass
class TrackConfig:
    """Options of :func:`track_photos`."""

    size: int = 256  # output crop side in pixels
    fov_deg: float = 30.0  # assumed field of view across the longer photo side (fit.default_intrinsics)
    extent_m: float = DEFAULT_EXTENT_M  # crop field at the head's depth (crop.py)
    max_rms: float = 0.06  # refuse a photo whose landmark RMS exceeds this fraction of its face size
    use_silhouette: bool = False  # also fit side views to the person mask's outline (silhouette.py; docs/tracking-log.md: no gain with Face Mesh landmarks)
    # register the photos' poses to each other photometrically after the landmark fit (photoalign.py), by default only
    # those the fit turns beyond where its landmarks saturate (align.free_min_yaw_deg; docs/tracking-log.md, "Registering the turned photos")
    photo_align: bool = True
    fit: FitConfig = field(default_factory=FitConfig)
    matting: MattingConfig = field(default_factory=MattingConfig)
    align: PhotoAlignConfig = field(default_factory=lambda: PhotoAlignConfig(free_min_yaw_deg=TURNED_MIN_YAW_DEG))

    @classmethod
    def with_photo_align(cls, mode: str = "turned", **kwargs) -> "TrackConfig":
        """A config whose photometric registration is ``mode``: ``"off"``, ``"turned"`` (the default:
        photos turned at least ``TURNED_MIN_YAW_DEG``) or ``"all"`` (every photo but the reference).
        ``kwargs`` set the other fields. Raises ``ValueError`` for another mode."""
        if mode not in PHOTO_ALIGN_MODES:
            raise ValueError(f"photo registration must be one of {', '.join(PHOTO_ALIGN_MODES)}, got {mode!r}")
        align = PhotoAlignConfig(free_min_yaw_deg=TURNED_MIN_YAW_DEG if mode == "turned" else 0.0)
        return cls(photo_align=mode != "off", align=align, **kwargs)


@dataclass
class TrackedPhotos:
    """Everything the tracker found for ``V`` photos."""

    crops: np.ndarray  # [V, S, S, 3] uint8 (padding = BACKGROUND_RGB; not matted)
    masks: np.ndarray  # [V, S, S] float32 alpha in [0, 1]
    cameras: Cameras  # [V] of the crops
    photo_cameras: Cameras | list[Cameras]  # per photo, of the full photo (sizes may differ)
    expressions: np.ndarray  # [V, 53] ict53
    landmarks: list[np.ndarray]  # V x [N, 2] detected, in photo pixels (layout below)
    fit: FitResult
    mask_given: list[bool]
    layout: str = "mediapipe"  # landmark layout: "mediapipe" (Face Mesh points) or "dlib68"
    residuals: list[np.ndarray] = field(default_factory=list)  # V x [N, 2] fitted minus detected, pixels
    alignment: PhotoAlignResult | None = None  # the photometric registration (None when off or a single photo)


def _as_photo(img, i: int, name: str) -> np.ndarray:
    a = np.asarray(img)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=2)
    if a.ndim != 3 or a.shape[2] not in (3, 4):
        raise ValueError(f"{name}: expected an RGB image [H, W, 3], got shape {list(a.shape)}")
    if a.dtype != np.uint8:
        if np.issubdtype(a.dtype, np.floating) and a.size and a.max() <= 1.0:
            a = np.round(a * 255.0)
        a = np.clip(a, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(a[..., :3])


def _as_mask(m, shape: tuple[int, int], name: str) -> np.ndarray:
    m = np.asarray(m)
    if m.ndim == 3:
        m = m[..., 0] if m.shape[-1] in (1, 3, 4) else m[0]
    m = m.astype(np.float32) / 255.0 if m.dtype == np.uint8 else m.astype(np.float32)
    if m.shape != shape:
        raise ValueError(f"{name}: mask must have the photo's size {list(shape)}, got {list(m.shape)}")
    return np.clip(m, 0.0, 1.0)


def track_photos(
    images: list[np.ndarray],  # V x [H_i, W_i, 3] uint8 RGB
    config: TrackConfig | None = None,
    masks: list[np.ndarray | None] | None = None,  # V x [H_i, W_i] alpha (uint8 or float) or None
    names: list[str] | None = None,  # used in error messages
    detector=None,  # a faces.FaceDetector (default: load_face_detector())
    identity: np.ndarray | None = None,  # [100] fixed identity; estimated when None
    focal_35mm: list[float | None] | None = None,  # V x EXIF 35 mm-equivalent focal length (mm) or None
) -> TrackedPhotos:
    """Track photos of **one** person (shared identity); see the package doc.

    Intrinsics: one focal length for the set. When any photo carries an EXIF 35 mm-equivalent
    focal length, their median is used for every photo (``fit.intrinsics_from_35mm``, the photos
    of one person are assumed to come from one camera); otherwise ``config.fov_deg`` across the
    longer side (``fit.default_intrinsics``). Errors (``NoFaceError``, ``SeveralFacesError``,
    ``TinyFaceError``, ``ValueError``) name the photo.
    """
    from .faces import load_face_detector

    cfg = config or TrackConfig()
    if not images:
        raise ValueError("need at least one photo to track, got none")
    if cfg.size < 16:
        raise ValueError(f"size must be at least 16 pixels, got {cfg.size}")
    names = names or [f"photo {i}" for i in range(len(images))]
    masks = list(masks) if masks is not None else [None] * len(images)
    if len(masks) != len(images) or len(names) != len(images):
        raise ValueError(f"got {len(images)} photos, {len(masks)} masks and {len(names)} names")
    det = detector or load_face_detector()
    photos = [_as_photo(im, i, n) for i, (im, n) in enumerate(zip(images, names))]
    exif = [float(f) for f in (focal_35mm or []) if f is not None and 4.0 <= float(f) <= 2000.0]
    f35 = float(np.median(exif)) if exif else None
    lms, Ks = [], []
    for img, name in zip(photos, names):
        _, lm = det.detect_one(img, name)
        lms.append(lm)
        h, w = img.shape[:2]
        Ks.append(intrinsics_from_35mm(w, h, f35) if f35 is not None else default_intrinsics(w, h, cfg.fov_deg))
    model = LandmarkModel.from_head_model(num_identity=cfg.fit.num_identity, layout=getattr(det, "layout", "dlib68"))
    targets = None
    if cfg.use_silhouette:
        targets = []
        for v, img in enumerate(photos):
            face = float(np.linalg.norm(lms[v].max(0) - lms[v].min(0)))
            try:
                m = _as_mask(masks[v], img.shape[:2], names[v]) if masks[v] is not None else person_mask(img)
                targets.append(SilhouetteTarget.from_mask(m, face))
            except (ImportError, ValueError) as e:  # no segmentation model, or an empty / full mask
                logger.info("%s: no outline constraint (%s)", names[v], e)
                targets.append(None)
    fit = fit_landmarks(np.stack(lms), np.stack(Ks), cfg.fit, model, identity=identity, silhouettes=targets)
    for v, name in enumerate(names):
        logger.info("%s: landmark RMS %.2f px, distance %.2f m", name, fit.rms_px[v], fit.translations[v, 2])
        face = float(np.linalg.norm(lms[v].max(0) - lms[v].min(0)))
        if not np.isfinite(fit.rms_px[v]) or fit.rms_px[v] > cfg.max_rms * face or fit.translations[v, 2] <= 0:
            raise ValueError(
                f"cannot place the head in {name}: the fitted head model misses its landmarks by {fit.rms_px[v]:.1f} px RMS "
                f"({100 * fit.rms_px[v] / face:.0f}% of the face size, at most {100 * cfg.max_rms:.0f}% accepted); "
                "is it a photo of the same person as the others, with the face unobstructed?"
            )
    alignment = None
    if cfg.photo_align and len(photos) > 1:
        given = [None if m is None else _as_mask(m, img.shape[:2], n) for m, img, n in zip(masks, photos, names)]
        alignment = register_photos(photos, fit.identity, fit.expressions, fit.rotations, fit.translations, fit.K, cfg.align,
                                    landmarks=lms, landmark_model=landmark_models(model, fit.rotations, cfg.fit), masks=given)  # fmt: skip
        fit.rotations, fit.translations = alignment.rotations, alignment.translations
        if cfg.align.identity_modes > 0:
            fit.identity = alignment.identity
        fit.rms_px = np.where(np.isfinite(alignment.rms_after), alignment.rms_after, fit.rms_px)
        for v, name in enumerate(names):  # the report's RMS is this one: say so for the photos the registration moved
            if np.isfinite(alignment.rms_after[v]) and alignment.rms_after[v] != alignment.rms_before[v]:
                logger.info("%s: registered to the other photos: landmark RMS %.2f px (was %.2f)", name, alignment.rms_after[v], alignment.rms_before[v])

    return tracked_photos_from_fit(photos, fit, lms, model, cfg, masks=masks, names=names, alignment=alignment)


def tracked_photos_from_fit(
    photos: list[np.ndarray],
    fit: FitResult,
    landmarks: list[np.ndarray],
    model: LandmarkModel,
    config: TrackConfig | None = None,
    masks: list[np.ndarray | None] | None = None,
    names: list[str] | None = None,
    alignment: PhotoAlignResult | None = None,
) -> TrackedPhotos:
    """The crops, cameras and masks of ``V`` photos for a given head fit: :func:`track_photos`
    after its fit, also for a fit made elsewhere (the held-out photo sets' true poses,
    ``refine/realsets.py --truth``).

    Args:
        photos: ``V`` x ``[H_i, W_i, 3]`` RGB (uint8, or other dtypes as :func:`track_photos` takes them).
        fit: the head in each photo (``fit.FitResult``: identity, expressions, ``R``, ``t``, ``K`` per photo).
        landmarks: ``V`` x ``[N, 2]`` the detected landmarks (photo pixels), in ``model``'s layout.
        model: the ``LandmarkModel`` of that layout (for the report's residuals).
        config: ``size``, ``extent_m`` and ``matting`` are used.
        masks: ``V`` x ``[H_i, W_i]`` alpha or None (matted from the fitted head).
        names: for error messages. alignment: kept in the result.
    Raises:
        ValueError: mismatched lengths, or a mask of another size than its photo.
    """
    from ..data.headmodel import HeadModel

    cfg = config or TrackConfig()
    V = len(photos)
    names = names or [f"photo {i}" for i in range(V)]
    masks = list(masks) if masks is not None else [None] * V
    if not (len(fit.rotations) == len(landmarks) == len(masks) == len(names) == V):
        raise ValueError(f"got {V} photos, {len(fit.rotations)} poses, {len(landmarks)} landmark sets, {len(masks)} masks and {len(names)} names")
    photos = [_as_photo(im, i, n) for i, (im, n) in enumerate(zip(photos, names))]
    lms = landmarks
    head = HeadModel.load()
    faces = head.visible_faces(eyelashes=False)
    bg = background_uint8()
    S = cfg.size
    crops, out_masks, crop_cams, photo_cams = [], [], [], []
    for v, (img, name) in enumerate(zip(photos, names)):
        H, W = img.shape[:2]
        cam = pose_to_cameras(fit.rotations[v], fit.translations[v], fit.K[v], W, H)
        photo_cams.append(cam)
        box = head_crop_box(fit.K[v], fit.translations[v], cfg.extent_m)
        ccam = crop_cameras(cam, box, S)
        crop = crop_array(img, box, S, bg)
        valid = crop_array(np.ones((H, W, 1), np.float32), box, S, [0.0])[..., 0] > 0.5
        if masks[v] is not None:
            m = crop_array(_as_mask(masks[v], (H, W), name)[..., None], box, S, [0.0])[..., 0]
        else:
            Kc = ccam.K[0].double().numpy()
            verts = head.vertices(fit.identity.astype(np.float32), fit.expressions[v].astype(np.float32))
            sil = head_silhouette(verts, faces, fit.rotations[v], fit.translations[v], Kc, S)
            lm = (head.landmarks(verts) @ fit.rotations[v].T + fit.translations[v]) @ Kc.T  # [68, 3] fitted, in the crop
            lm = lm[:, :2] / lm[:, 2:]
            m = matte_from_head(crop, sil, Kc[0, 0] / fit.translations[v, 2], lm[57, 1], valid, cfg.matting, face_points=lm)
        crops.append(crop)
        out_masks.append(np.clip(m, 0, 1).astype(np.float32))
        crop_cams.append(ccam)
    same = len({(c.width, c.height) for c in photo_cams}) == 1
    return TrackedPhotos(
        crops=np.stack(crops),
        masks=np.stack(out_masks),
        cameras=Cameras.stack(crop_cams),
        photo_cameras=Cameras.stack(photo_cams) if same else photo_cams,
        expressions=fit.expressions.astype(np.float32),
        landmarks=lms,
        fit=fit,
        mask_given=[m is not None for m in masks],
        layout=model.layout,
        residuals=[fit.project(model, v) - lms[v] for v in range(len(lms))],
        alignment=alignment,
    )


def track_request(images: list[np.ndarray], size: int, masks=None):
    """Server entry point: photos without cameras -> model-ready crops.

    Args:
        images: V x ``[H, W, 3]`` uint8 RGB photos of one person.
        size: output side ``S`` (the crops can be passed to ``FastGHA.prepare``, which resizes).
        masks: optional V x ``[H, W]`` alpha (uint8 or float) or None entries.
    Returns:
        crops ``[V, 3, S, S]`` float32 in [0, 1] (not matted; padding = BACKGROUND_RGB),
        ``Cameras [V]`` of the crops, masks ``[V, 1, S, S]`` float32, expressions ``[V, 53]`` float32.
    Raises:
        faces.FacesUnavailableError (an ImportError) when the ``faces`` extra is missing;
        ValueError (NoFaceError / SeveralFacesError / TinyFaceError) naming the photo.
    """
    res = track_photos(list(images), TrackConfig(size=int(size)), masks=masks)  # names: "photo <i>"
    crops = torch.from_numpy(res.crops).permute(0, 3, 1, 2).float() / 255.0
    m = torch.from_numpy(res.masks)[:, None]
    return crops, res.cameras, m, torch.from_numpy(res.expressions)


def known_camera_fit_config() -> FitConfig:
    """The default ``FitConfig`` of :func:`track_known_cameras`: the photo-only defaults with a
    stronger identity prior (``identity_weight`` 10 instead of 0.3). Measured on held-out synthetic
    subjects (seeds 1000200-1000205, the evaluation protocol's 4 inputs, 2 of them profiles without
    landmarks): mean distance to the true face mesh 10.2 / 8.6 / 7.9 mm at weights 0.3 / 3 / 10;
    with the weak prior the identity absorbs the Face Mesh points' systematic offsets from the
    model's vertices (fitted identity norms twice the truth's)."""
    return FitConfig(identity_weight=10.0)


def track_known_cameras(
    images,
    cameras: "Cameras | list[Cameras]",
    config: FitConfig | None = None,
    detector=None,
    names: list[str] | None = None,
    max_rms: float = TrackConfig.max_rms,
    masks=None,
):
    """Photos **with** cameras -> the person's head in the cameras' world (``fit.fit_known_cameras``).

    The photo-only path (:func:`track_photos`) makes its own head-centric cameras; photos that come
    with cameras (held-out synthetic renders, a request's ``cameras.json``) keep theirs, and the
    head is placed in their world: one identity, one expression per photo, one rigid head -> world
    transform. Photos where the detector finds no face (profiles beyond ~80 degrees), several or
    a too small one, or whose landmarks the fitted head misses by more than ``max_rms`` x the face
    size, do not take part; they get a neutral expression.

    Args:
        images: ``[V, 3, H, W]`` float in [0, 1] or uint8 tensor, or ``V`` x ``[H_i, W_i, 3]`` uint8 arrays.
        cameras: ``Cameras [V]`` of those images, or ``V`` single ``Cameras`` (photos of different sizes).
        config: ``fit.FitConfig``; detector: a ``faces`` detector (default ``load_face_detector()``).
        masks: optional ``[V, H, W]`` / ``[V, 1, H, W]`` tensor or ``V`` x ``[H_i, W_i]`` alpha (or None
            entries): the outline of each turned photo's face joins the fit (``fit.fit_known_cameras``),
            profiles without landmarks included.
    Returns:
        ``(model.surface.HeadSurface [V] with head_to_world, fit.KnownCameraFit)``.
    Raises:
        faces.FacesUnavailableError (an ImportError) without the ``faces`` extra; ValueError when no
        photo gives usable landmarks, or on mismatched shapes.
    """
    from ..model.surface import HeadSurface
    from .faces import load_face_detector

    if isinstance(images, torch.Tensor):
        t = images.detach().cpu()
        t = t if t.dtype == torch.uint8 else (t.float().clamp(0, 1) * 255.0).round().to(torch.uint8)
        photos = [np.ascontiguousarray(x.permute(1, 2, 0).numpy()) for x in t]
    else:
        photos = [_as_photo(im, i, f"photo {i}") for i, im in enumerate(images)]
    if isinstance(cameras, Cameras):
        flat = cameras.flatten()
        cams = [flat[i : i + 1] for i in range(len(flat.K))]
    else:
        cams = [c.flatten()[0:1] for c in cameras]
    V = len(photos)
    names = names or [f"photo {i}" for i in range(V)]
    if len(cams) != V:
        raise ValueError(f"track_known_cameras: got {V} photos but {len(cams)} cameras")
    for img, cam, name in zip(photos, cams, names):
        if img.shape[:2] != (cam.height, cam.width):
            raise ValueError(f"track_known_cameras: {name} is {img.shape[1]}x{img.shape[0]} but its camera describes {cam.width}x{cam.height}")
    det = detector or load_face_detector()
    cfg = config or known_camera_fit_config()
    lms: list[np.ndarray | None] = []
    for img, name in zip(photos, names):
        try:
            lms.append(det.detect_one(img, name)[1])
        except ValueError as e:  # NoFaceError / SeveralFacesError / TinyFaceError
            logger.debug("%s: no landmarks (%s); it keeps a neutral expression", name, e)
            lms.append(None)
    layout = getattr(det, "layout", "dlib68")
    model = LandmarkModel.from_head_model(num_identity=cfg.num_identity, layout=layout)
    K = np.stack([c.K[0].double().numpy() for c in cams])
    w2c = np.stack([c.w2c[0].double().numpy() for c in cams])
    mlist = None
    if masks is not None:
        ms = list(masks.detach().cpu().unbind(0)) if isinstance(masks, torch.Tensor) else list(masks)
        if len(ms) != V:
            raise ValueError(f"track_known_cameras: got {V} photos but {len(ms)} masks")
        mlist = [None if m is None else _as_mask(m.numpy() if isinstance(m, torch.Tensor) else m, photos[i].shape[:2], names[i]) for i, m in enumerate(ms)]  # uint8: /255
    fit = fit_known_cameras(lms, K, w2c, cfg, model, masks=mlist)
    bad = [v for v in range(V) if lms[v] is not None and fit.rms_px[v] > max_rms * float(np.linalg.norm(lms[v].max(0) - lms[v].min(0)))]
    if bad:  # a photo the shared head cannot explain (wrong camera, another person): fit without it
        logger.info("%s: the shared head misses the landmarks (RMS %s px); fitted without them",
                    ", ".join(names[v] for v in bad), ", ".join(f"{fit.rms_px[v]:.1f}" for v in bad))  # fmt: skip
        lms = [None if v in bad else lm for v, lm in enumerate(lms)]
        fit = fit_known_cameras(lms, K, w2c, cfg, model, masks=mlist)
    for v, name in enumerate(names):
        if fit.detected[v]:
            logger.debug("%s: landmark RMS %.2f px through the given camera; own pose %.1f deg / %.0f mm from the shared one",
                        name, fit.rms_px[v], fit.pose_spread_deg[v], fit.pose_spread_mm[v])  # fmt: skip
    return HeadSurface(fit.identity, fit.expressions, fit.head_to_world), fit
