"""The virtual robot: physics, a virtual pigpiod and a virtual Marvelmind."""
