"""kneeseat core: settle rigid bodies by collision detection (US 6,708,142); no ROS."""
