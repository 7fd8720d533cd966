"""quadobs/observability"""
