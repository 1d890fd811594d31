"""The FastGHA HTTP + WebSocket server (``fastgha serve``; protocol in ``docs/protocol.md``).

``fastgha_core`` is imported first, before any module here imports torch: it sets the OpenMP
environment defaults (``fastgha_core.perf.apply_env_defaults``) that only reach torch's thread pool
when they are set before torch loads. Without this, ``import server.app`` (plain
``uvicorn --factory server.app:create_app``) or ``from server.protocol import unpack_frame`` ran
torch with spinning idle threads and logged a warning saying so.
"""

import fastgha_core  # noqa: F401  (must precede torch; see above)
