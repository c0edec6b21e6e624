"""Plant simulator of the drift stack: a double-track car richer than the controller model.

``params`` (config/sim/plants/<vehicle>.yaml), ``model`` (the casadi equations of motion),
``road`` (friction field), ``plant`` (``Plant.reset`` / ``Plant.step(command)``), ``driver``
(semi-automated mode), ``scenario`` (config/scenarios), ``simulator`` (a scenario on the
plant), ``lockstep``, ``can_vehicle`` (the plant behind the car's CAN end), ``metrics``; ROS
only in ``nodes/``.
"""
