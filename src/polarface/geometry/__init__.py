"""polarface.geometry"""
