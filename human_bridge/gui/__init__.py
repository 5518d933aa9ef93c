"""``khgrl human gui``: a pygame window in which a person watches an actor and drags its robot.

:mod:`~human_bridge.gui.app` holds the state and what mouse and keys do, :mod:`~human_bridge.gui.view` draws
it, :mod:`~human_bridge.gui.main` is the window process (window, network pump, screenshots).
"""
