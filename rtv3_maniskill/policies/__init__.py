"""LeRobot policies of the project.

``rtv3``: the RT-V3 prior (paper, Sec. IV) as a LeRobot 0.4.4 policy. Importing
:mod:`rtv3_maniskill.policies.rtv3` registers the ``rtv3`` policy type with LeRobot.
"""
