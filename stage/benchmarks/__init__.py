"""Benchmarks run by ``stage bench NAME``; one module per benchmark."""
