"""quadobs/evaluation"""
