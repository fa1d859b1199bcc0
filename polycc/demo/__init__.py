"""Synthetic scenes: the demo flight arena (:mod:`.arena`) and arenas built from real captures
(:mod:`.arenas`), all in metres, z up.
"""
