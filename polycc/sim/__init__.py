"""Simulation on top of the pipeline: cffi builds of the very C files that fly (:mod:`.kernel_ffi`,
:mod:`.app_ffi`, firmware API shims in ``shims/``), the bare-metal Cortex-M4 harness
(:mod:`.kernel_arm`, ``arm/``), vehicle models (:mod:`.dynamics`), host SITL flights
(:mod:`.sitl`) and the simulated Crazyflie that cflib connects to (:mod:`.sitl_device`,
:mod:`.crtp_device`, :mod:`.device_server`).
"""
