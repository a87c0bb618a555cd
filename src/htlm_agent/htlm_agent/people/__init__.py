"""A person in the team: the page of each person who plays an agent, and the commander's page, without ROS."""
