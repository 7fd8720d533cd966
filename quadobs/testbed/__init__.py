"""quadobs/testbed"""
