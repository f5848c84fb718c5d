"""Inverse rendering stages (paper Sec. 5): static polarimetric maps, then biophysical parameters.

:mod:`polarface.inverse.polarimetric` recovers eta, alpha_s, alpha_ss, rho_s, rho_ss, rho_sss_bar and
the displacement map in texture space; :mod:`polarface.inverse.biophysical` fits the chromophore maps
to rho_sss_bar; :mod:`polarface.inverse.ior` is the single-view sphere refractive-index measurement of
the paper's validation table.
"""
