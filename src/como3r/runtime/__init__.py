"""como3r.runtime"""
