"""polarface.inverse"""
