"""The robot: the Panda's kinematic and collision model, the motion planner, the NEO QP twist
controller and its safety filter, the ManiSkill twist agent, and pure scene geometry."""
