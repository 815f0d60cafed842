"""Real recordings in, one clip type out.

Every loader returns a :class:`MotionClip` (metres, Z up, NaN = missing).
Formats: BVH (:mod:`.bvh`), CMU ASF/AMC (:mod:`.asf_amc`), C3D (:mod:`.c3d`),
MoCap Toolbox CSV (:mod:`.markers_csv`), TRC (:mod:`.trc`), QTM's 3D TSV
(:mod:`.qtm_tsv`), OptiTrack Motive's CSV (:mod:`.motive_csv`) -- the text exports share
:mod:`.marker_table`'s rules -- and derived joint-position CSV (:mod:`.positions_csv`);
:func:`load_clip` dispatches on the extension.
:mod:`.pointsets` derives the paper's 14 body points; :mod:`.synthetic` makes a
synthetic walker for demos and fast tests.
"""
from .clip import MotionClip
from .load import find_recordings, load_clip, load_clips
from .pointsets import BODY14, derive_body14, detect_marker_set, left_right_pairs, mirror_name, to_point_set
from .synthetic import synthesize

__all__ = ["MotionClip", "load_clip", "load_clips", "find_recordings", "BODY14", "to_point_set", "derive_body14",
           "detect_marker_set", "mirror_name", "left_right_pairs", "synthesize"]
