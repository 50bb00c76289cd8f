"""The demos: the whole pipeline on a knee (`demo`, with its table and bag in `demo_table`),
tracker mode end to end (`tracker_demo`), and the child processes both start (`children`).

Nothing is imported here: the demos run as `python -m kneeseat_ros.demos.<demo>`, and a
package that imported them would execute them twice.
"""
