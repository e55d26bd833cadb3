"""Annotation QA: scores of every input annotation against the estimate (anomalies.py)."""
