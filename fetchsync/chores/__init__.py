"""The robot chores the verbs run, laptop side: build, lint, snapshot, accounts,
workspace status, shell helpers, several robots at once (``fleet``).
"""
