"""Sensor simulator and effect library.

``simulate(trajectory, SensorModel(...), effects=[("current_hard_iron", {"kx": 0.1})])`` gives a
:class:`~mkc_stream.io.recording.Recording` of a magnetometer (with accelerometer, gyroscope
and aux columns) along a generated or recorded trajectory. ``EFFECTS`` is the effect library:
each effect's forward model and its diagnosis form, declared together (:mod:`.effects`).
:mod:`.presets` holds ready-made simulations (``presets.sweep``: the synthetic calibration stream).
"""
from .effects import EFFECTS, Effect, Evidence, Param, parse_effect
from .sensor import SensorModel, Simulation, simulate
from .trajectory import Trajectory, from_recording, generate

__all__ = ["EFFECTS", "Effect", "Evidence", "Param", "SensorModel", "Simulation", "Trajectory",
           "from_recording", "generate", "parse_effect", "simulate"]
