"""Packed scene -> ``polytopes.h`` + ``manifest.json`` + ``scene.bin`` (:mod:`.header`); the
jinja2 templates (structure only) ship as package data in ``templates/``.
"""
