"""The estimators' compiled code: CasADi-generated C for the models (`codegen`, cached by content hash), the
hand-written C loops (`ukf.c`, `gn.c`, `btd.c`, `lu.c`) and their ctypes wrappers (`ukf_native`,
`block_tridiagonal`); each falls back to numpy/LAPACK or CasADi's interpreter without a compiler."""
