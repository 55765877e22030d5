//! Direct O(N^2) sum: the test oracle.
