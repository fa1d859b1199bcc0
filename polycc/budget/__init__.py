"""Merge family + budgets -> the packed on-board scene: outward plane reduction (:mod:`.reduce`),
candidate selection under the flash, half-plane and rate budgets (:mod:`.select`) and the
Cortex-M4 cycle model of one kernel evaluation (:mod:`.cycle_model`).
"""
