"""Helpers the tests share (not tests themselves): short campaigns run in-process on the twins, synthetic run
files with known answers, and the protocol doubles of the drivers' byte-exact tests."""
