"""Scenes and data shared by several experiments (and tests); they write no results themselves."""
