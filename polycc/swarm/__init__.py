"""Swarms on the fast simulator: N independent instances of the host-built app (:mod:`.instances`),
the decentralized coverage controller of seed 003 (:mod:`.coverage`), the N-drone loop
(:mod:`.sim`) and its plot (:mod:`.plot`).  docs/swarm.md."""
