//! File formats: Middlebury .flo, .npy, PNG sequences, JSON Lines.
