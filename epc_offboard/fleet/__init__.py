"""Fleet sharing over Zenoh: the wire codec and the sharing session.
"""
