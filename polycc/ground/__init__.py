"""Talking to a real (or simulated) Crazyflie: fly it with cflib (:mod:`.fly`) and build and
flash the firmware with the app (:mod:`.flash`).
"""
