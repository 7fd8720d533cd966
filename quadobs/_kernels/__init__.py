"""quadobs/_kernels"""
