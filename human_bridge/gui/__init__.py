"""``khgrl human gui``: a pygame window in which a person watches an actor and drags its robot, for any task.

:mod:`~khgrl.human_bridge.gui.app` holds the state and what mouse and keys do, :mod:`~khgrl.human_bridge.gui.view` draws
it (the task's views by :class:`khgrl.common.tasks.render.TaskRenderer`), :mod:`~khgrl.human_bridge.gui.main` is the
window
process (window, network pump, the run's task from the actors, screenshots), :mod:`~khgrl.human_bridge.gui.task`
builds a task descriptor here and the exploration band's projector.
"""
