//! Natural Helmholtz-Hodge decomposition (Bhatia et al. 2014) of a flow patch.
