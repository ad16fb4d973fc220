"""Choosing a configuration: sweeps (one MLflow child run per configuration), ranking, promotion."""
