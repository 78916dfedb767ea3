"""Experiments that stopped at their go/no-go, kept beside it out of the package (docs/correction.md)."""
