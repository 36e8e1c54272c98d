"""The faces of the package: the campaign (the main job), the command line and the demo. The CLI is the
only place that selects a matplotlib backend.
"""
