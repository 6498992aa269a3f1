"""como3r.io"""
