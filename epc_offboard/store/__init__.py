"""The controller library on disk (SQLite).
"""
