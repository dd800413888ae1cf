"""RT-V3 shared control on ManiSkill3 and LeRobot."""
