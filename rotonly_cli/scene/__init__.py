"""The data model every stage shares: plain data, no file I/O.

``types``: what a reader knows about a project (``SfMScene``: views, intrinsics, poses,
keypoints, pairs, structure); ``view_graph``: the edges between views with their relative
poses, statuses and diagnostics, and the graph queries and filters of the stages;
``ids``: id shifts and renumbering between COLMAP's and OpenMVG's conventions;
``tracks``: the tracks of a view graph's matches, shared by the stages of one run.
"""
