"""The Python side of the C contract with ``firmware_app/``: the scene layout and its packing
(:mod:`.layout`, format 3), the bit-exact float32 reference of the kernel (:mod:`.barrier`,
:mod:`.fastmath`) and the app's status codes, params and logs (:mod:`.app`).
"""
