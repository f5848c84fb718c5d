"""polarface.skin"""
