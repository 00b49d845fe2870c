"""Sim-to-real gap diagnosis: where the real-vs-twin gap lies, which effect explains it, how far it shrinks (docs/simreal.md)."""
