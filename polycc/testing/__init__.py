"""Helpers for tests and benchmarks (synthetic polytopes, a fake cflib device model); not used by
the pipeline.
"""
