"""Importers of public datasets: real-robot logs written as scenario files (they may import io and models, never estimators)."""
