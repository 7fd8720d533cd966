"""quadobs/studies"""
