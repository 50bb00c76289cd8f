"""kneeseat ROS 2 layer: table_server node, session recording, replay."""
