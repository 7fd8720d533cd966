"""quadobs/core"""
