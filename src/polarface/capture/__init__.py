"""polarface.capture"""
