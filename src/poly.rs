//! Multivariate polynomials: terms, evaluation, least-squares fitting, order search.
