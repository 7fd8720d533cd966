"""quadobs/sets"""
