"""The 2D open-vocabulary segmentation task (``task=ovss``): its task class
(:mod:`.task`, ``OVSSTask``), the engine (:mod:`.engine`, ``OVSSEngine``), the pass settings an
export carries (:mod:`.settings`) and the training callback that evaluates every epoch (:mod:`.callback`,
``ReSiRegEval``). May be imported by the task table (by name), ``resireg_train.training``'s
run (the callback, through ``conf/callbacks/``) and the CLIs.
"""
