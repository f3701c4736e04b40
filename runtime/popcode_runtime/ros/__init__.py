"""A robot's own formats: ROS 2 bags in, ``vision_msgs`` out, through the optional ``ros`` extra (rosbags)."""
