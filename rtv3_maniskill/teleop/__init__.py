"""A person at the controls: input devices, the interactive session, its display and render process,
grasp actions, trial outcomes, the session recorder and the user study."""
