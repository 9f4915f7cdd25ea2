"""Simulation: scans with known truth (the paper's study, phantoms, the built-in demo)."""
