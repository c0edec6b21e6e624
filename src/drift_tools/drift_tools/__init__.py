"""Tools of the drift stack: process launcher, MCAP recorder, topic inspection, bag reading."""
