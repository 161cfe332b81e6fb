"""The simulated aircraft (model.md §8): its own physics, scenarios, off-line runs and truth.

The CANopen slave nodes build on `AircraftPhysics.next_sample()` and `ChannelCodec`.
"""
from .offline import ChannelCodec, SimRun, quantise_sample, simulate, stack_samples
from .physics import AircraftPhysics, SimSample
from .scenarios import Scenario, list_scenarios, load_scenario
from .truth import read_truth, write_truth

__all__ = [
    "AircraftPhysics", "ChannelCodec", "Scenario", "SimRun", "SimSample", "list_scenarios",
    "load_scenario", "quantise_sample", "read_truth", "simulate", "stack_samples",
    "write_truth",
]
