"""Forward models built from a stage and a GP: the AFM (eq. 5-14), the extended physical model,
the EAFM (AFM + GP posterior as CasADi graphs), and training the residual model.
"""
