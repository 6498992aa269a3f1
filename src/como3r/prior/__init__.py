"""como3r.prior"""
