"""Sketch control (paper Sec. 3.2, App. B–D): a user's arrow or oval and the
current fluid state → external accelerations that MPM applies over the next
``T_ctr`` frames.

* :mod:`~hybridmpm.control.sketch` — the sketch format and the one rasteriser;
* :mod:`~hybridmpm.control.reverse` — control targets by reverse simulation
  (the paper's kinematic formula and a tracking variant solved through MPM),
  smoothing;
* :mod:`~hybridmpm.control.controller` — :class:`Controller` (none, constant
  force, PD attraction, model-predictive control, oracle replay, the
  diffusion model) making :class:`Plan` s, which are simulator forcings;
  each scene's default method and what a viewer offers
  (:func:`default_method`, :func:`scene_methods`);
* :mod:`~hybridmpm.control.mpc` — the 16-number force field, the
  cross-entropy method and MPC on the coarse-grid model;
* :mod:`~hybridmpm.control.targets` — the sketch's geometry (each particle's
  target point, the geometry the network reads, the smoothstep ramp);
* :mod:`~hybridmpm.control.prior` — the free-motion prior (a coarse MPM rollout);
* :mod:`~hybridmpm.control.diffusion` — the Fluid ControlNet's numpy half:
  temporal basis, schedule, DDIM, the onnxruntime sampler
  (:class:`ControlModel`); its torch half and the control cases it trains on
  are in :mod:`hybridmpm.train.control` (the ``train`` extra);
* :mod:`~hybridmpm.control.metrics` — how close a controlled run lands;
* :mod:`~hybridmpm.control.episode` — one controlled episode with its metrics.

>>> from hybridmpm.control import Controller, Sketch
>>> plan = Controller.for_scene("water2d").plan(sim, Sketch.arrow([0.3, 0.2], [0.7, 0.4]))
>>> sim.forcing = plan      # MPM applies it for the next T_ctr frames
"""

from hybridmpm.control.controller import METHODS, Controller, Plan, default_method, scene_methods, track_path
from hybridmpm.control.diffusion import ControlModel
from hybridmpm.control.episode import Episode, control_episode
from hybridmpm.control.metrics import control_metrics
from hybridmpm.control.mpc import MpcSettings, PlanStopped
from hybridmpm.control.reverse import A_MAX, clip_norm, reverse_kinematic, reverse_tracking, smooth
from hybridmpm.control.sketch import KINDS, Sketch, render_sketch, sketch_from_image, sketch_from_png, sketch_from_trajectory
from hybridmpm.control.targets import pd_targets

__all__ = [
    "A_MAX",
    "KINDS",
    "METHODS",
    "ControlModel",
    "Controller",
    "Episode",
    "MpcSettings",
    "Plan",
    "PlanStopped",
    "Sketch",
    "clip_norm",
    "control_episode",
    "control_metrics",
    "default_method",
    "pd_targets",
    "render_sketch",
    "reverse_kinematic",
    "reverse_tracking",
    "scene_methods",
    "sketch_from_image",
    "sketch_from_png",
    "sketch_from_trajectory",
    "smooth",
    "track_path",
]
