"""Looking at a build: the stored polytopes as meshes (:mod:`.meshes`, for ``polycc export``) and the
browser view of splats, cover and flights (:mod:`.viewer`, for ``polycc view``). World frame, metres."""
