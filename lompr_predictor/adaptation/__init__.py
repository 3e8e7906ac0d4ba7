# SPDX-License-Identifier: Apache-2.0
"""Online adaptation: the predictor node's attempts to fine-tune its model on its own samples.

`scheduler` (ROS-free, in the node's process) decides when an attempt is due, starts it as a
child process and records how it ended; `attempt` is that child process (it loads the
trainer, which the node never does); `outcome` is what passes between them, typed.
"""
