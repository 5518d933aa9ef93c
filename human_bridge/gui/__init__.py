"""``khgrl human gui``: a pygame window in which a person watches an actor and drags its robot, for any task.

:mod:`~human_bridge.gui.app` holds the state and what mouse and keys do, :mod:`~human_bridge.gui.view` draws
it (the task's views by :class:`common.task_render.TaskRenderer`), :mod:`~human_bridge.gui.main` is the window
process (window, network pump, the run's task from the actors, screenshots), :mod:`~human_bridge.gui.task`
builds a task descriptor here and the exploration band's projector.
"""
