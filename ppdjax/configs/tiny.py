"""Tiny preset: runs on a laptop CPU in a few minutes."""

import ml_collections


def get_config() -> ml_collections.ConfigDict:
  config = ml_collections.ConfigDict()
  config.name = "tiny"
  config.seed = 0
  # Physics demo: one random tower under the paper's four pushes.
  config.demo = ml_collections.ConfigDict()
  config.demo.num_blocks = 4  # 2..5
  config.demo.steps = 256
  config.demo.backend = "mjx"  # the engine whose trajectories are shown
  config.demo.reference_backend = "mujoco"  # compared against; "" to skip
  config.demo.example_samples = 128  # density samples for the shipped example (paper: 512)
  # Block-tower dataset (python -m ppdjax.generate).
  config.data = ml_collections.ConfigDict()
  config.data.kind = "towers"  # or "tools" (configs/tools.py: num_tools, tools_per_shard)
  config.data.num_towers = 16
  config.data.towers_per_shard = 4
  config.data.configs_per_tower = 8
  config.data.image_size = 64
  config.data.steps = 256
  config.data.num_blocks = 0  # blocks per tower: 0 draws 2..5; 2 for the tools' pretraining
  config.data.rotate = 0.0  # radians; > 0 adds the paper's rotation noise (tools pretraining)
  config.data.size_noise = 0.0
  # the engine that simulates the data, and that evaluation then uses: "mjx", or "box_plane"
  # (faster on a GPU, closer to MuJoCo C); "mujoco" makes a marked C variant read through MJX
  config.data.backend = "mjx"
  config.data.split_fractions = (0.8, 0.1, 0.1)
  config.data.render_workers = 0  # processes rendering in parallel (0: this process)
  # The PPD network (paper appendix; ppdjax.nn.model).
  config.model = ml_collections.ConfigDict()
  config.model.feature = 64  # f_V, f_I, f_T and f
  config.model.hidden = 64  # LSTM hidden size (trajectory encoder and generator)
  config.model.generator_layers = 3
  config.model.dropout = 0.5
  config.model.voxel_width = 1  # channel multiplier of the voxel encoder (1: the paper's)
  config.model.voxel_coords = False  # voxel centres as 3 extra input channels (CoordConv)
  config.model.voxel_keep = 1  # pool the voxels down to keep^3 (1: the paper's; 4 keeps position)
  config.model.resnet_width = 16  # 64 is ResNet-18 proper (paper preset); 16 for CPUs
  # the ResNet's compute type ("bfloat16": convolutions in bfloat16, parameters float32)
  config.model.image_dtype = "float32"
  config.model.image_weights = ""  # optional .npz of converted torchvision ResNet-18 weights
  config.model.num_pushes = 4
  config.model.trajectory_unroll = 1  # time steps per scan iteration of the trajectory LSTMs
  config.model.max_primitives = 5
  config.model.use_voxels = True  # ablation switches: a disabled encoder's feature is 0
  config.model.use_image = True
  config.model.use_trajectory = True
  # True: the density head reads a second LSTM stack of its own, so the density loss does
  # not move the geometry's LSTMs or the voxel encoder (ppdjax.nn.model.PPD._step; the
  # tools preset); False: the paper's one generator for both
  config.model.density_branch = False
  # > 0: the density branch also reads the velocities over the first this many recorded
  # steps after each push (ppdjax.nn.motion.early_motion; needs density_branch)
  config.model.early_motion_steps = 0
  # Training (python -m ppdjax.train).
  config.train = ml_collections.ConfigDict()
  config.train.seed = 0
  config.train.batch_size = 16  # global, split over all devices
  # Over several devices, BatchNorm's statistics: "global" (the whole batch, all-reduced at
  # every normalisation: the math of one device) or "per_device" (each device's share; the
  # step's one collective is the average of its gradients at the end). One device: the same.
  config.train.batch_norm = "global"
  config.train.learning_rate = 1e-3  # Adam, beta = (0.9, 0.999), as in the appendix
  config.train.schedule = "constant"  # or "cosine": decay to 0 over all steps
  config.train.warmup_steps = 0  # > 0: the rate rises linearly from 0 over these steps
  config.train.clip_norm = 0.0  # > 0: gradients clipped to this global norm before Adam
  config.train.stream_steps = 0  # phase 0: voxels of fresh towers only (dataset.stream)
  config.train.geometry_steps = 20  # phase 1: geometry only (w = 0)
  config.train.joint_steps = 40  # phase 2: geometry + w x density
  config.train.density_weight = 0.5  # w of Eq. 4-5 (docs/training.md says why 0.5)
  config.train.density_ramp_steps = 0  # > 0: w rises linearly over the joint phase's first steps
  config.train.end_weight = 1.0  # the end token's loss, in every phase (losses.loss_fn)
  config.train.geometry_weight = 1.0  # the dataset's geometry loss
  config.train.stream_weight = 0.0  # > 0: phases 1-2 add a stream batch's geometry loss
  config.train.augment = True  # stream batches under random symmetries of the square about z
  config.train.init_from = ""  # a workdir whose matching parameters start this run
  config.train.log_every = 10
  config.train.eval_every = 30  # validation and checkpoint
  config.train.eval_batches = 4  # validation batches per evaluation (0: the whole split)
  config.train.keep_checkpoints = 3
  config.train.prefetch = 2  # batches read ahead in a background thread
  # The density estimator (ppdjax.nn.estimator; python -m ppdjax.train_estimator): reads
  # the fitted boxes and the trajectories, trained on simulated towers (no rendering).
  config.estimator = ml_collections.ConfigDict()
  config.estimator.seed = 0
  config.estimator.pool_size = 512  # simulated training towers (fresh geometry each)
  config.estimator.val_size = 128
  config.estimator.steps = 100
  config.estimator.batch_size = 32
  config.estimator.learning_rate = 1e-3  # AdamW, warm-up then cosine decay
  config.estimator.warmup_steps = 10
  config.estimator.weight_decay = 1e-4
  config.estimator.clip_norm = 1.0
  config.estimator.label_sigma = 1.0  # slots: Gaussian targets about the true slot
  config.estimator.box_noise = 0.002  # m: face jitter of the boxes it reads (fitted boxes' error)
  config.estimator.channels = (16, 16, 32, 32)  # 1-D convolutions over time, stride 2 each
  config.estimator.hidden = 64
  config.estimator.layers = 2
  config.estimator.steps_in = config.data.steps
  config.estimator.num_pushes = config.model.num_pushes
  config.estimator.max_primitives = config.model.max_primitives
  config.estimator.eval_every = 50
  # Evaluation and decomposition (python -m ppdjax.evaluate; the demo's last steps).
  config.eval = ml_collections.ConfigDict()
  config.eval.samples = 8  # density samples per object (the paper: 512)
  config.eval.refine = False  # LM refinement through MJX (about a minute to compile on a CPU)
  config.eval.refine_steps = 12
  config.eval.batch_size = 8
  config.eval.prior_weight = 0.0  # +Sample: distance - tau log prior (m per nat; 0: the paper's)
  config.eval.fit = False  # also the +Fit rows: boxes fitted to the voxels (infer.fit)
  config.eval.depth = False  # also the +Fit(depth) rows: then refined against the depth image
  config.eval.refine_prior = 0.0  # > 0: with a fit, +Refine is a MAP step (refine.refine_densities)
  config.eval.refine_jacobian = "forward"  # forward | differences | central (refine.py)
  config.eval.estimator = ""  # a trained density estimator's folder: adds the +Est rows
  config.eval.estimator_weight = 1.0  # its log-probabilities' weight beside the network's
  config.eval.joint = False  # also +Joint: faces and densities fitted together (infer.joint)
  config.eval.true_shapes = False  # also the oracle rows on the true boxes
  # Table 4's sampling baselines on whole batches spread over about this many objects
  # (evaluation.evaluate; 0: every object)
  config.eval.table4_objects = 0
  # +Fit+Sample also draws each candidate's faces within this many voxels of the fitted
  # ones (infer.faces; 0: the fitted boxes only)
  config.eval.face_spread = 0.0
  config.eval.image_fit = False  # +Fit then refined against the image's edges (image_fit)
  return config
