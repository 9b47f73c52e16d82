"""Red stickers in video frames (paper Sec. 5.3): HSV threshold, connected components,
sub-pixel centroids.

A pixel is sticker-red when its hue lies within `HUE_TOLERANCE` of red (OpenCV's hue
runs 0-179 and wraps at red), and its saturation and value clear `min_saturation` and
`MIN_VALUE`. Each connected blob of `min_area` to `max_area` pixels is one sticker (a
larger one is a red surface, e.g. brick); its centre is the blob's centroid weighted by
saturation, so a blurred edge counts by how red it is. The default saturation bound
(200) keeps the project's brick texture (saturation about 0.77, i.e. 196) out.
"""

from __future__ import annotations

import cv2
import numpy as np

HUE_TOLERANCE = 10  # OpenCV hue units (2 degrees each)
MIN_SATURATION = 200
MIN_VALUE = 60
MIN_AREA = 4  # pixels


def red_mask(frame: np.ndarray, min_saturation: int = MIN_SATURATION
             ) -> tuple[np.ndarray, np.ndarray]:
  """(H, W) bool mask of sticker-red pixels and (H, W) float32 weights: the saturation of
  pixels of red hue (0 elsewhere), by which a blurred or anti-aliased edge counts."""
  hsv = cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2HSV)
  hue, sat, val = hsv[..., 0].astype(np.int32), hsv[..., 1], hsv[..., 2]
  red_hue = np.minimum(hue, 180 - hue) <= HUE_TOLERANCE
  red = red_hue & (sat >= min_saturation) & (val >= MIN_VALUE)
  return red, np.where(red_hue, sat, 0).astype(np.float32)


def detect_stickers(frame: np.ndarray, min_area: int = MIN_AREA, max_area: int | None = None,
                    min_saturation: int = MIN_SATURATION) -> np.ndarray:
  """(M, 2) sub-pixel centres (x right, y down, pixels) of the red blobs of one
  (H, W, 3) uint8 RGB frame, largest blob first (max_area None: 1 % of the frame).

  A blob's centre is the weighted centroid of the blob grown by one pixel, so its soft
  edge (blur, anti-aliasing) counts on every side alike."""
  red, weight = red_mask(frame, min_saturation)
  if max_area is None:
    max_area = int(0.01 * red.size)
  count, labels, stats, _ = cv2.connectedComponentsWithStats(red.astype(np.uint8), 8)
  keep = [i for i in range(1, count)
          if min_area <= stats[i, cv2.CC_STAT_AREA] <= max_area]
  keep.sort(key=lambda i: -stats[i, cv2.CC_STAT_AREA])
  grown = cv2.dilate(labels.astype(np.float32), np.ones((3, 3), np.uint8)).astype(np.int64)
  grown = np.where(labels > 0, labels, grown)  # a pixel between two blobs keeps its own
  ys, xs = np.nonzero(grown)
  lab, w = grown[ys, xs], weight[ys, xs]
  sums = np.stack([np.bincount(lab, w * xs, count), np.bincount(lab, w * ys, count),
                   np.bincount(lab, w, count)], -1)
  return np.array([sums[i, :2] / sums[i, 2] for i in keep], np.float64).reshape(-1, 2)
