"""Simulated scenarios for ``relpoint simulate`` (pure computation; the CLI writes the log)."""

from relpoint.simulation.config import MOVER_MOTIONS, SCENARIOS, SimulationConfig
from relpoint.simulation.scenario import SimulatedStep, Simulation, simulate

__all__ = ["MOVER_MOTIONS", "SCENARIOS", "SimulatedStep", "Simulation", "SimulationConfig", "simulate"]
