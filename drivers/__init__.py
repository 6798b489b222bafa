"""The hardware edge of robotd (encoders, motors, Marvelmind) and its stand-ins (the virtual robot)."""
