"""The offboard service: the TaskGroup that wires link, loops, store and fleet together.
"""
