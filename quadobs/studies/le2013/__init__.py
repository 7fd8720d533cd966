"""quadobs/studies/le2013"""
