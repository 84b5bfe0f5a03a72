"""The datasets: caption streaming for training (:mod:`.captions`), the 2D segmentation sets
(:mod:`.segmentation`; ADE20K :mod:`.ade20k`, ORAD-3D :mod:`.orad3d`, the OVSS field's
:mod:`.voc`, :mod:`.context`, :mod:`.coco`, :mod:`.cityscapes`), ScanNet scenes (:mod:`.scannet`), Replica and
TartanAir scenes (:mod:`.replica`, :mod:`.tartanair`, on :mod:`.posed3d`), the generated scenes
of tests and smoke runs (:mod:`.synthetic`, :mod:`.scannet_room`, :mod:`.room_bag`), and the
dataset table (:mod:`.specs`, torch-free: every kind, its keys, rules and tasks).

Imports ``resireg`` and the config helpers. May be imported by ``resireg_train.evaluation``,
the config checks (the table) and the CLIs; the training run builds its data module from
``conf/data/`` (``_target_``).
"""
