"""ResNet-18 image encoder in Flax NNX, laid out like torchvision's so converted weights load."""

from __future__ import annotations

import numpy as np
import jax
import jax.numpy as jnp
from flax import nnx

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)
BN_MOMENTUM = 0.9  # torch's 0.1


def _conv(cin, cout, k, stride, rngs, dtype=None):
  return nnx.Conv(cin, cout, (k, k), strides=stride, padding=k // 2, use_bias=False,
                  kernel_init=nnx.initializers.kaiming_normal(), dtype=dtype, rngs=rngs)


def _bn(c, rngs, zero=False, dtype=None):
  init = nnx.initializers.zeros if zero else nnx.initializers.ones
  return nnx.BatchNorm(c, momentum=BN_MOMENTUM, scale_init=init, dtype=dtype, rngs=rngs)


class BasicBlock(nnx.Module):
  """Two 3×3 convolutions with a residual connection (He et al. 2016)."""

  def __init__(self, cin: int, cout: int, stride: int, *, rngs: nnx.Rngs, dtype=None):
    self.conv1 = _conv(cin, cout, 3, stride, rngs, dtype)
    self.bn1 = _bn(cout, rngs, dtype=dtype)
    self.conv2 = _conv(cout, cout, 3, 1, rngs, dtype)
    self.bn2 = _bn(cout, rngs, zero=True, dtype=dtype)  # each block starts as the identity
    self.downsample = (nnx.List([_conv(cin, cout, 1, stride, rngs, dtype),
                                 _bn(cout, rngs, dtype=dtype)])
                       if stride != 1 or cin != cout else None)

  def __call__(self, x, train: bool):
    y = nnx.relu(self.bn1(self.conv1(x), use_running_average=not train))
    y = self.bn2(self.conv2(y), use_running_average=not train)
    if self.downsample is not None:
      conv, bn = self.downsample
      x = bn(conv(x), use_running_average=not train)
    return nnx.relu(x + y)


class ResNet18(nnx.Module):
  """ResNet-18 whose classifier is a fully connected layer to `out_features`.

  `width` is the first stage's channel count (64 in the paper; the tiny preset narrows it
  for CPUs). Images are uint8 (B, H, W, 3), normalised with ImageNet statistics so that
  converted torchvision weights see what they were trained on. `dtype` is the
  convolutions' and normalisations' compute type (None: float32; "bfloat16" halves the
  memory traffic on an accelerator); parameters stay float32 and the features leave in
  float32.
  """

  def __init__(self, out_features: int, width: int = 64, *, rngs: nnx.Rngs, dtype=None):
    self.conv1 = _conv(3, width, 7, 2, rngs, dtype)
    self.bn1 = _bn(width, rngs, dtype=dtype)
    chans = [width, 2 * width, 4 * width, 8 * width]
    cin = width
    for i, (c, s) in enumerate(zip(chans, (1, 2, 2, 2))):
      setattr(self, f"layer{i + 1}", nnx.List([BasicBlock(cin, c, s, rngs=rngs, dtype=dtype),
                                               BasicBlock(c, c, 1, rngs=rngs, dtype=dtype)]))
      cin = c
    self.fc = nnx.Linear(cin, out_features, rngs=rngs)

  def __call__(self, image_BHWx3: jax.Array, train: bool) -> jax.Array:
    x = (image_BHWx3.astype(jnp.float32) / 255.0 - IMAGENET_MEAN) / IMAGENET_STD
    x = nnx.relu(self.bn1(self.conv1(x), use_running_average=not train))
    x = nnx.max_pool(x, (3, 3), strides=(2, 2), padding=((1, 1), (1, 1)))
    for layer in (self.layer1, self.layer2, self.layer3, self.layer4):
      for block in layer:
        x = block(x, train)
    return self.fc(x.astype(jnp.float32).mean(axis=(1, 2)))


def load_torchvision_weights(net: ResNet18, path: str) -> None:
  """Loads a torchvision ResNet-18 state dict saved as .npz (fc is skipped: it is replaced).

  Make the file where torch is installed:
    `np.savez(path, **{k: v.numpy() for k, v in torchvision.models.resnet18(
        weights="IMAGENET1K_V1").state_dict().items()})`

  Raises:
    ValueError naming the file and the key that is missing or of the wrong shape.
  """
  try:
    weights = dict(np.load(path))
  except (OSError, ValueError) as e:
    raise ValueError(f"cannot read ResNet-18 weights from {path}: {e}") from e
  names = {"weight": None, "bias": "bias", "running_mean": "mean", "running_var": "var"}
  used = 0
  for key, value in weights.items():
    *parts, leaf = key.split(".")
    if parts[0] == "fc" or leaf == "num_batches_tracked":
      continue
    module = net
    for p in parts:
      module = module[int(p)] if p.isdigit() else getattr(module, p, None)
      if module is None:
        raise ValueError(f"{path}: unexpected key {key!r} (not a ResNet-18 state dict?)")
    if isinstance(module, nnx.Conv):
      target, value = module.kernel, np.transpose(value, (2, 3, 1, 0))  # OIHW -> HWIO
    elif leaf == "weight":
      target = module.scale
    else:
      target = getattr(module, names[leaf])
    if target.shape != value.shape:
      raise ValueError(f"{path}: {key} has shape {value.shape}, the model expects "
                       f"{target.shape} (is model.resnet_width 64?)")
    target.value = jnp.asarray(value, target.dtype)
    used += 1
  if used != 100:  # 20 convolutions + 20 batch norms x 4 arrays
    raise ValueError(f"{path}: found {used} of the 100 ResNet-18 arrays (fc excluded)")
