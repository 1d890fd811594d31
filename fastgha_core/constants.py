"""Project-wide constants with one meaning everywhere."""

# Input photos are foreground-matted: the background is replaced by this one colour (RGB in [0, 1]),
# in synthetic data, training, the server's preprocessing and rendering alike (docs/conventions.md, Images).
BACKGROUND_RGB: tuple[float, float, float] = (1.0, 1.0, 1.0)

# Current version of the avatar file format written by ``fastgha_core.io.save_avatar``.
AVATAR_FORMAT_VERSION = 1
