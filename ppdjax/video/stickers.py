"""Red stickers in video frames (paper Sec. 5.3): HSV threshold, connected components,
sub-pixel centroids.

A pixel is sticker-red when its hue lies within `HUE_TOLERANCE` of red (OpenCV's hue
runs 0-179 and wraps at red), and its saturation and value clear `MIN_SATURATION` and
`MIN_VALUE`. Each connected blob of at least `min_area` pixels is one sticker; its centre
is the blob's centroid weighted by saturation, so a blurred edge counts by how red it is.
"""

from __future__ import annotations

import cv2
import numpy as np

HUE_TOLERANCE = 10  # OpenCV hue units (2 degrees each)
MIN_SATURATION = 110
MIN_VALUE = 60
MIN_AREA = 4  # pixels


def red_mask(frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """(H, W) bool mask of sticker-red pixels and (H, W) float32 saturation of an RGB frame."""
  hsv = cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2HSV)
  hue, sat, val = hsv[..., 0].astype(np.int32), hsv[..., 1], hsv[..., 2]
  red = (np.minimum(hue, 180 - hue) <= HUE_TOLERANCE) & (sat >= MIN_SATURATION) & (
      val >= MIN_VALUE)
  return red, sat.astype(np.float32)


def detect_stickers(frame: np.ndarray, min_area: int = MIN_AREA) -> np.ndarray:
  """(M, 2) sub-pixel centres (x right, y down, pixels) of the red blobs of one
  (H, W, 3) uint8 RGB frame, largest blob first."""
  red, sat = red_mask(frame)
  count, labels, stats, _ = cv2.connectedComponentsWithStats(red.astype(np.uint8), 8)
  keep = [i for i in range(1, count) if stats[i, cv2.CC_STAT_AREA] >= min_area]
  keep.sort(key=lambda i: -stats[i, cv2.CC_STAT_AREA])
  ys, xs = np.nonzero(labels)
  lab = labels[ys, xs]
  w = sat[ys, xs]
  out = np.zeros((len(keep), 2), np.float64)
  sums = np.stack([np.bincount(lab, w * xs, count), np.bincount(lab, w * ys, count),
                   np.bincount(lab, w, count)], -1)
  for j, i in enumerate(keep):
    out[j] = sums[i, :2] / sums[i, 2]
  return out
