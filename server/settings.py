"""Server settings from ``FASTGHA_*`` environment variables (pydantic-settings).

Every limit the server enforces is a field here, so operators can tune them without code.
``get_settings()`` reads the environment each time it is called; ``create_app(settings)``
takes an explicit ``Settings`` (tests and ``fastgha serve`` build one and pass it in).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from fastgha_core.commands import MAX_REFINE_STEPS, MAX_VIEW_BLEND_TAU_DEG, view_blend_tau_problem

__all__ = ["MAX_VIEW_BLEND_TAU_DEG", "Settings", "get_settings"]


_REPO_STATIC = Path(__file__).resolve().parent.parent / "client_demo" / "static"


def _split_csv(value: str) -> list[str]:
    return [v.strip() for v in value.split(",") if v.strip()]


def _read_keys_file(path: Path) -> list[str]:
    """API keys from a file: one per line or comma-separated; blank lines and ``#`` comments ignored."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise ValueError(f"api_keys_file {str(path)!r} cannot be read ({type(e).__name__}: {getattr(e, 'strerror', None) or e})") from None
    keys: list[str] = []
    for line in text.splitlines():
        line = line.split("#", 1)[0]
        keys += [k for k in _split_csv(line) if k not in keys]
    if not keys:
        raise ValueError(f"api_keys_file {str(path)!r} holds no key")
    return keys


class Settings(BaseSettings):
    """All server settings; each field reads the environment variable ``FASTGHA_<NAME>``."""

    model_config = SettingsConfigDict(env_prefix="FASTGHA_", extra="ignore", protected_namespaces=())

    # ------------------------------------------------------------ model and storage
    model: str = Field("tiny", description='model to load: "tiny", "paper" or a folder with config.json')
    device: str = Field("auto", description='"auto" (cuda when available, else cpu), "cpu" or "cuda[:N]"')
    data_dir: Path = Field(Path("fastgha-data"), description="folder where avatars are persisted")
    warmup: bool = Field(True, description="reconstruct once and render a few frames at start-up")
    warmup_frames: int = Field(3, ge=0, le=100)
    mlp_precision: Literal["auto", "fp32", "bf16"] = Field(
        "auto", description='deformation MLP precision: "auto" = timed at start-up (fp32 vs bf16 on the served chunk shape), bf16 only when clearly faster'
    )
    cuda_graphs: bool = Field(
        False, description="with a compiled MLP on CUDA: replay it as CUDA graphs (torch.compile mode reduce-overhead)"
    )
    compile: Literal["auto", "on", "off"] = Field(
        "auto",
        description='torch.compile the deformation MLP at start-up: "auto" = on when a C++ compiler is found (CPU) or on CUDA; needs warmup',
    )

    # ------------------------------------------------------------ security
    api_keys: str = Field(
        "",
        description="comma-separated API keys required to create avatars; empty = creation is open (set it in production)",
    )
    api_keys_file: Path | None = Field(
        None,
        description="file with API keys (one per line or comma-separated, # comments); added to api_keys. "
        "Keeps keys out of the process list and the environment of child processes",
    )
    cors_origins: str = Field(
        "", description='comma-separated allowed CORS origins; empty = CORS off, "*" = any. Also gates WebSocket Origin'
    )
    forwarded_allow_ips: str = Field(
        "127.0.0.1",
        description="comma-separated addresses of the reverse proxies whose X-Forwarded-* headers are trusted "
        "(fastgha serve --proxy-headers); never * unless nothing but the proxy can reach the server",
    )

    # ------------------------------------------------------------ connections (fastgha serve; see docs/deploy.md)
    header_timeout_seconds: float = Field(
        10.0, gt=0, description="a connection must send a complete request head this soon after it opens or after its last response"
    )
    body_timeout_seconds: float = Field(
        120.0, gt=0, description="a request body must arrive completely this soon after its head"
    )
    keep_alive_seconds: float = Field(5.0, gt=0, le=300, description="idle keep-alive connections are closed after this long")
    max_request_head_bytes: int = Field(
        16384, ge=1024, le=1024 * 1024, description="largest request line + headers (431 beyond)"
    )
    max_url_bytes: int = Field(8192, ge=256, description="longest request target, path and query (414 beyond)")
    limit_concurrency: int = Field(
        1024, ge=8, description="open connections + running requests above which new requests get 503 at once"
    )
    ws_send_timeout_seconds: float = Field(
        10.0, gt=0, description="a stream whose client reads nothing for this long is closed with 4408"
    )
    ws_send_buffer_bytes: int = Field(
        512 * 1024, ge=0, description="kernel send buffer of a stream's socket (SO_SNDBUF); 0 = the system's autotuning (up to ~4 MB)"
    )

    # ------------------------------------------------------------ upload limits
    max_upload_bytes: int = Field(32 * 1024 * 1024, ge=1024, description="largest POST /v1/avatars body")
    max_image_pixels: int = Field(16_777_216, ge=64, description="largest width*height of one uploaded image")
    max_images: int = Field(8, ge=1, le=64, description="most images per avatar")
    max_concurrent_reconstructions: int = Field(1, ge=1, description="reconstructions running at once; others queue")
    min_avatar_gaussians: int = Field(
        256, ge=1, description="a reconstruction with fewer Gaussians holds no head (e.g. cameras far from it): 422"
    )
    surface_depth: bool = Field(
        True, description="photos without cameras, or sent with a 'head' part: put every pixel's Gaussian on the tracked head (one geometry for all views; docs/model-card.md)"
    )
    surface_depth_cameras: Literal["off", "replace", "blend"] = Field(
        "off",
        description="photos WITH cameras: fit the head through them (faces extra) and put the Gaussians on it: 'replace' every "
        "pixel, 'blend' the bare face only (the rest the network's depth joined to it); off = the network's depth. "
        "Off by default: on held-out synthetic subjects 'replace' lowers novel-view PSNR and 'blend' is within 0.2 dB of the "
        "network's depth, above it on two draws of four subjects and below it on two (docs/model-card-log.md, "
        "\"Known cameras: one fitted head instead of the network's depth\")",
    )
    view_blend_tau_deg: float | None = Field(
        None,
        description="frames of avatars with per-view data (built on a tracked head): each input view's Gaussians are weighted by "
        "exp(-(angle of its camera to the frame's camera - the smallest such angle) / tau), tau in degrees; 0 = off (every view "
        "unweighted); unset = the model's own (gaussians.view_blend_tau_deg, 20 for tiny and paper)",
    )
    mirror_views: bool | None = Field(
        None,
        description="avatars built on a tracked head: add the mirror image of every photo turned by 30 degrees or more as a virtual "
        "view of the side of the head no photo shows (fills side views with cheek, ear and hair instead of stripes; +24-42% "
        "Gaussians and frame time); unset = the model's own (gaussians.mirror_views, on for tiny)",
    )
    same_person_check: bool = Field(
        True,
        description="refuse (422 different_people) photos of one avatar whose dlib face descriptors split into several people "
        "(faces extra; photos without a frontal face are not compared; without dlib nothing is checked)",
    )
    same_person_max_distance: float = Field(
        0.6, gt=0, le=2, description="largest face-descriptor distance that links two photos as the same person (dlib's threshold: 0.6)"
    )
    refine_steps: int | Literal["auto"] = Field(
        "auto",
        description="test-time refinement after each reconstruction (fastgha_core.refine). auto (default): avatars on a tracked head "
        "(photos without cameras, or with fastgha track's head part) get REFINE_PRESETS['photos'] (colours only, 30 steps: identity "
        "closer to the person on every real set), avatars on the network's depth (photos with cameras) REFINE_PRESETS['default'] "
        "(60 steps, with the photos' expressions fitted through their cameras when the faces extra is installed: sharper eyes "
        "and brows, +1.0 to +1.7 dB on the shipped samples; docs/model-card.md); N (0-1000): N steps for every avatar with the "
        "preset that fits it (refine_preset_for); 0 = off",
    )

    # ------------------------------------------------------------ streaming
    max_output_size: int = Field(1024, ge=16, le=8192, description="cap on the output width and height of a frame")
    default_jpeg_quality: int = Field(85, ge=1, le=100)
    default_camera_distance: float = Field(1.0, gt=0, description="metres from the head centre of the default camera")
    default_camera_fov_deg: float = Field(20.0, gt=0, lt=180)
    ws_max_message_bytes: int = Field(65536, ge=256, description="largest WebSocket message a client may send")
    ws_max_messages_per_second: float = Field(240.0, gt=0, description="sustained client message rate per socket")
    ws_abuse_factor: float = Field(
        4.0, ge=1.0, description="a socket sending faster than this multiple of the rate limit is closed"
    )
    max_streams_per_avatar: int = Field(4, ge=1)
    max_streams_total: int = Field(64, ge=1)
    render_workers: int = Field(2, ge=1, description="threads rendering frames (off the event loop)")

    # ------------------------------------------------------------ cache and expiry
    cache_max_bytes: int = Field(2 * 1024**3, ge=0, description="byte budget of the in-memory avatar LRU")
    avatar_ttl_seconds: float = Field(
        7 * 24 * 3600.0, ge=0, description="idle avatars are deleted after this long; 0 = never"
    )
    expiry_interval_seconds: float = Field(300.0, gt=0, description="how often expired avatars are swept")

    # ------------------------------------------------------------ creation jobs (server/jobs.py, docs/protocol.md)
    max_queued_jobs: int = Field(8, ge=0, description="creations waiting for a slot; more answer 503 queue_full")
    max_jobs_per_client: int = Field(4, ge=1, description="creations queued or running per API key (or address without keys); more answer 429")
    max_queued_upload_bytes: int = Field(128 * 1024 * 1024, ge=1024, description="upload bytes held by queued and running creations; more answer 503")
    max_request_pixels: int = Field(134_217_728, ge=64, description="largest sum of width*height over the images and masks of one request (read from headers, before decoding)")
    decode_max_side: int = Field(1024, ge=64, description="photos are downscaled while decoding so that their longer side is at most this (never below the model's input size)")
    job_ttl_seconds: float = Field(600.0, gt=0, description="finished creation jobs answer their status resource for this long")
    creation_sched_idle: bool = Field(
        True, description="creation threads run under Linux's SCHED_IDLE policy (a render thread that wakes takes their core at once); false = only the nice value below"
    )
    creation_nice: int = Field(10, ge=0, le=19, description="nice value of the creation threads where SCHED_IDLE is off or unavailable")

    # ------------------------------------------------------------ misc
    static_dir: Path | None = Field(
        None, description="folder served at / (the browser demo); default client_demo/static when it exists"
    )
    samples_dir: Path | None = Field(
        None, description="sample subjects served under /v1/samples; default: the shipped fastgha_core/assets/samples"
    )

    @field_validator("model")
    @classmethod
    def _non_empty(cls, v: str) -> str:
        if not v.strip():
            raise ValueError("model must not be empty")
        return v

    @field_validator("refine_steps", mode="before")
    @classmethod
    def _refine_steps(cls, v):
        if isinstance(v, str) and v.strip().lower() == "auto":
            return "auto"
        try:
            n = int(v)
        except (TypeError, ValueError):
            raise ValueError(f"refine_steps must be auto or a number of steps 0-{MAX_REFINE_STEPS}, got {v!r}") from None
        if not 0 <= n <= MAX_REFINE_STEPS:
            raise ValueError(f"refine_steps must be auto or a number of steps 0-{MAX_REFINE_STEPS}, got {n}")
        return n

    @field_validator("view_blend_tau_deg")
    @classmethod
    def _tau(cls, v: float | None) -> float | None:
        problem = None if v is None else view_blend_tau_problem(v)
        if problem:
            raise ValueError(problem)
        return v

    @field_validator("api_keys_file")
    @classmethod
    def _keys_file_readable(cls, v: Path | None) -> Path | None:
        if v is not None:
            _read_keys_file(v)  # fail at start-up, not at the first request
        return v

    @property
    def api_key_list(self) -> list[str]:
        keys = _split_csv(self.api_keys)
        if self.api_keys_file is not None:
            keys += [k for k in _read_keys_file(self.api_keys_file) if k not in keys]
        return keys

    @property
    def cors_origin_list(self) -> list[str]:
        return _split_csv(self.cors_origins)

    def resolved_static_dir(self) -> Path | None:
        """The folder to serve at ``/``, or None when there is none."""
        d = self.static_dir if self.static_dir is not None else _REPO_STATIC
        return d if d.is_dir() else None

    def resolved_bf16(self, device: str) -> bool:
        if self.mlp_precision != "auto":
            return self.mlp_precision == "bf16"
        from fastgha_core.perf import fast_bf16

        return fast_bf16(device)

    def resolved_compile(self, device: str) -> bool:
        if self.compile != "auto":
            return self.compile == "on"
        if device.startswith("cuda"):
            return True
        from fastgha_core.perf import cpp_compiler

        return cpp_compiler() is not None

    def resolved_device(self) -> str:
        if self.device != "auto":
            return self.device
        import torch

        return "cuda" if torch.cuda.is_available() else "cpu"


def get_settings() -> Settings:
    """Settings from the environment (``FASTGHA_*``); override by passing your own to ``create_app``."""
    return Settings()
