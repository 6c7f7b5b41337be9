"""Simulated scenarios for ``relpoint simulate`` (pure computation; the CLI writes the log)."""

from relpoint.simulation.config import SCENARIOS, SimulationConfig
from relpoint.simulation.scenario import SimulatedStep, Simulation, simulate

__all__ = ["SCENARIOS", "SimulatedStep", "Simulation", "SimulationConfig", "simulate"]
