"""From video to trajectories (paper Sec. 5.3): red sticker detection, minimum-distance
matching, PnP with Levenberg-Marquardt, resampling to the simulator's dt."""

from ppdjax.video.pose import solve_pnp
from ppdjax.video.stickers import detect_stickers
from ppdjax.video.track import TrackingError, track_poses

__all__ = ["TrackingError", "detect_stickers", "solve_pnp", "track_poses"]
