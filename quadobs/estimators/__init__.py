"""quadobs/estimators"""
