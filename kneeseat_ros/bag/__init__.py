"""Session bags: rosbag2-style MCAP directories written by the node (`recorder`, with the
message definitions of `msgdefs`), read back (`session`), repaired after a crash
(`recovery`), replayed (`replay`) and made from angle trajectories (`make_bag`).

Nothing is imported here: `replay`, `make_bag` and `recovery` run as `python -m
kneeseat_ros.bag.<tool>`, and a package that imported them would execute them twice.
"""
