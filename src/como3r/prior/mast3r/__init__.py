"""como3r.prior.mast3r"""
