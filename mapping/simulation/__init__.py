"""Simulated SCENES and SEQUENCES: rendered rooms, paper sweeps and brackets written to folders with ground truth.

Every hidden quantity is known. The other homes of made-up data: :mod:`radiometry.simulation` is the camera
these sequences are taken with (response, vignetting, exposure, noise); :mod:`mapping.datasets.simulated` reads
the folders written here; :mod:`mapping.datasets.in_memory` is a dataset over frames already in memory.

- :mod:`~mapping.simulation.room`: a furnished, textured, lit room from a seed (:func:`make_room`,
  :func:`load_room`), with the true radiance at any 3D point (:meth:`Room.radiance_at`).
- :mod:`~mapping.simulation.render`: ray casting (Open3D ``RaycastingScene``) into depth and radiance.
- :mod:`~mapping.simulation.sensor`: a structured-light depth sensor model.
- :mod:`~mapping.simulation.trajectory`: a hand-held walk and a white-paper sweep; TUM poses.
- :mod:`~mapping.simulation.targets`: the white-paper scene and an HDR chart.
- :mod:`~mapping.simulation.sequences`: ``simulate_room``, ``simulate_paper``, ``simulate_brackets``
  (folders with ground truth) and their in-memory ``iter_*`` counterparts.
- :func:`sample_sequence`: small cached samples for the demo and tests.
"""

from mapping.simulation.render import Renderer, RenderResult
from mapping.simulation.room import Room, RoomParams, load_room, make_room
from mapping.simulation.samples import sample_sequence
from mapping.simulation.scene import Face, Lighting, PointLight, TexturedScene
from mapping.simulation.sensor import DepthSensor
from mapping.simulation.sequences import (DEPTH_SCALE, KINDS, MANIFEST, SimFrame, bracket_times, iter_brackets,
                                          iter_paper_frames, iter_room_frames, light_step, resolve_camera,
                                          simulate_brackets, simulate_paper, simulate_room, timestamps)
from mapping.simulation.targets import PaperScene, hdr_chart, make_paper_scene
from mapping.simulation.trajectory import (HandheldMotion, PaperSweep, handheld_trajectory, look_at,
                                           motion_per_frame, paper_trajectory, pose_to_tum, quaternion_to_rotation,
                                           room_trajectory, rotation_to_quaternion, tum_to_pose)

__all__ = [
    "DEPTH_SCALE", "DepthSensor", "Face", "HandheldMotion", "KINDS", "Lighting", "MANIFEST", "PaperScene",
    "PaperSweep", "PointLight", "RenderResult", "Renderer", "Room", "RoomParams", "SimFrame", "TexturedScene",
    "bracket_times", "handheld_trajectory", "hdr_chart", "iter_brackets", "iter_paper_frames", "iter_room_frames",
    "light_step", "load_room", "look_at", "make_paper_scene", "make_room", "motion_per_frame", "paper_trajectory",
    "pose_to_tum", "quaternion_to_rotation", "resolve_camera", "room_trajectory", "rotation_to_quaternion", "sample_sequence", "simulate_brackets", "simulate_paper",
    "simulate_room", "timestamps", "tum_to_pose",
]
