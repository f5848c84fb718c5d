"""polarface.texture"""
