"""CiA 402 drives on EtherCAT (CoE) through SOEM: the segment, the CoE mailbox, the process
data, and the master that runs the CAN master's mode table, state machine and safety on them."""
