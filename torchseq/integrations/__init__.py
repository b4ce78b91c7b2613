"""Bridges to other tools' harnesses: :mod:`torchseq.integrations.eventlab` (Event-LAB)."""
