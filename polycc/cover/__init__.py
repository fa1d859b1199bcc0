"""V+ -> the PolyMerge merge family H^N..H^1 (Sec. V-B..D): clusters (:mod:`.clusters`), weighted
set cover (:mod:`.setcover`), iterative merging (:mod:`.merge`), the family file (:mod:`.family`),
and :func:`build_cover`, which runs them (:mod:`.build`). World frame, metres.
"""

from polycc.cover.build import COVER_COSTS, DEFAULT_MERGE_COST, build_cover
from polycc.cover.family import CoverFamily

__all__ = ["COVER_COSTS", "DEFAULT_MERGE_COST", "CoverFamily", "build_cover"]
