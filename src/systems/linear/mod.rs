//! Linear-Gaussian systems: the discretisation every continuous linear model shares.

pub mod discretise;
