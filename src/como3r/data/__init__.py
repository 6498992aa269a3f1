"""como3r.data"""
