"""The scripted expert's plans for the tasks beyond ``insertion`` (whose plan is ``expert.ScriptedExpert``'s
own): ``pickup``, ``extraction`` and ``running_suture``, which strings the others together."""
