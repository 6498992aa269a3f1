"""como3r.backend"""
