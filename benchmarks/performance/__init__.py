"""Speed: the daemon's rate, latency and CPU, the clients' and the ROS 2 output's costs."""
